"""Processes seen through Linux /proc, for the tests that check no process is left behind."""

from __future__ import annotations

from pathlib import Path

#: the tests that read /proc skip without it (macOS)
HAS_PROC = Path("/proc/self/stat").exists()


def _stat(pid: int | str) -> tuple[str, list[str]] | None:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat[stat.index("(") + 1 : stat.rindex(")")], stat[stat.rindex(")") + 2 :].split()


def children_of(pid: int) -> list[tuple[int, str]]:
    """Live (not zombie) child processes of ``pid``: (pid, name)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit() and (st := _stat(d.name)) is not None:
            name, fields = st
            if int(fields[1]) == pid and fields[0] != "Z":
                out.append((int(d.name), name))
    return out


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (exists and is not a zombie)."""
    st = _stat(pid)
    return st is not None and st[1][0] != "Z"
