"""A `.cti` that is a shared library but not a GenTL producer is skipped, never loaded.

Loading such a library through harvesters crashed the whole process (exit 139, no message):
the GenTL consumer calls entry points the library does not have. The checks that could
crash run in a child process, so that on a regression this test fails instead of killing
the test session.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from drivers.genicam import find_producers, producer_problem

pytestmark = [
    pytest.mark.timeout(120),
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="ELF producers (Linux)"),
]

NOT_A_PRODUCER = "is a shared library but not a GenTL producer"


@pytest.fixture
def plain_library(tmp_path: Path) -> Path:
    """A real shared library that is no GenTL producer (the C extension ctypes uses), as .cti."""
    import _ctypes

    bad = tmp_path / "bad"
    bad.mkdir()
    shutil.copy(_ctypes.__file__, bad / "x.cti")
    return bad / "x.cti"


def _run_cli(
    args: list[str], env_extra: dict[str, str], tmp_path: Path,
) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("GENICAM_GENTL64_PATH", "LENSLESSCAM_GENTL_PATH")}
    env.update(XDG_CACHE_HOME=str(tmp_path / "empty-cache"), **env_extra)
    code = "import sys, app.cli; sys.exit(app.cli.main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          env=env, timeout=90, check=False)


def test_devices_skips_a_library_that_is_not_a_producer_and_keeps_the_others(
    plain_library: Path, viky_cti: Path, tmp_path: Path,
) -> None:
    run = _run_cli(["devices", "--json"], {"GENICAM_GENTL64_PATH": str(plain_library.parent)},
                   tmp_path)
    assert run.returncode == 0, f"exit {run.returncode}: {run.stderr[-500:]}"
    out = json.loads(run.stdout)
    assert out["gentl_skipped"] == [
        f"GenTL producer {plain_library} skipped: it {NOT_A_PRODUCER} (it exports none of "
        "the GenTL functions GCInitLib, TLOpen, ...)"
    ]
    assert out["gentl_producers"] == [str(viky_cti)]
    assert [c["spec"] for c in out["cameras"] if c["backend"] == "genicam"] == [
        "genicam:0", "genicam:1", "genicam:2"]  # viky's three cameras are still listed


def test_an_explicit_producer_that_is_not_one_is_a_one_line_error(
    plain_library: Path, tmp_path: Path,
) -> None:
    run = _run_cli(["devices", "--producer", str(plain_library)], {}, tmp_path)
    assert run.returncode == 2, f"exit {run.returncode}: {run.stderr[-500:]}"
    assert run.stderr.strip().splitlines() == [
        f"lenslesscam devices: error: GenTL producer {str(plain_library)!r} {NOT_A_PRODUCER} "
        "(it exports none of the GenTL functions GCInitLib, TLOpen, ...)"
    ]


def test_opening_a_camera_on_a_library_that_is_not_a_producer_raises(
    plain_library: Path, tmp_path: Path,
) -> None:
    code = (
        "import sys\n"
        "from drivers.camera import CameraError\n"
        "from drivers.genicam import GenICamCamera, list_genicam_devices\n"
        "for call in (lambda: GenICamCamera(0, producer=sys.argv[1]).open(),\n"
        "             lambda: list_genicam_devices([sys.argv[1]])):\n"
        "    try:\n"
        "        call()\n"
        "    except CameraError as exc:\n"
        "        print(exc)\n"
    )
    run = subprocess.run([sys.executable, "-c", code, str(plain_library)], capture_output=True,
                         text=True, timeout=90, check=False)
    assert run.returncode == 0, f"exit {run.returncode}: {run.stderr[-500:]}"
    line = f"GenTL producer {plain_library} {NOT_A_PRODUCER}"
    assert [s.split(" (it exports")[0] for s in run.stdout.splitlines()] == [line, line]


def test_the_check_reads_the_file_without_loading_it(
    plain_library: Path, tlsimu_cti: Path, viky_cti: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    def no_child(*args: object, **kwargs: object) -> None:
        raise AssertionError("an ELF library with section headers needs no child process")

    monkeypatch.setattr(subprocess, "run", no_child)
    assert producer_problem(plain_library) == (
        f"{NOT_A_PRODUCER} (it exports none of the GenTL functions GCInitLib, TLOpen, ...)")
    assert producer_problem(tlsimu_cti) is None and producer_problem(viky_cti) is None
    maps = Path("/proc/self/maps").read_text()
    assert str(plain_library) not in maps  # not loaded into this process


def _patched(src: Path, dest: Path, offset: int, data: bytes) -> Path:
    raw = bytearray(src.read_bytes())
    raw[offset:offset + len(data)] = data
    dest.write_bytes(bytes(raw))
    return dest


def test_elf_files_this_process_cannot_load_are_named(
    plain_library: Path, tmp_path: Path,
) -> None:
    little = plain_library.read_bytes()[5] == 1
    u16 = (lambda v: v.to_bytes(2, "little" if little else "big"))  # noqa: E731
    cases = {
        "exe.cti": (16, u16(2), "is an executable, not a shared library"),
        "obj.cti": (16, u16(1), "is a relocatable object (.o), not a shared library"),
        "arm.cti": (18, u16(0xB7), "-bit library for ELF machine 183; this Python is"),
        "w32.cti": (4, b"\x01", "is a 32-bit library for ELF machine"),
    }
    for name, (offset, data, reason) in cases.items():
        why = producer_problem(_patched(plain_library, tmp_path / name, offset, data))
        assert why is not None and reason in why, (name, why)
    short = tmp_path / "short.cti"
    short.write_bytes(plain_library.read_bytes()[:4096])
    assert "truncated" in (producer_problem(short) or "")
    # none of them is usable: an explicit folder is refused, naming each file
    with pytest.raises(FileNotFoundError, match="holds no usable producer"):
        find_producers([tmp_path], use_environment=False, include_cache=False,
                       include_package=False)


def test_a_library_without_section_headers_is_checked_in_a_child_process(
    plain_library: Path, tlsimu_cti: Path, tmp_path: Path,
) -> None:
    raw = plain_library.read_bytes()
    little = raw[5] == 1
    shnum_at = 0x3C if raw[4] == 2 else 0x30
    zero = (0).to_bytes(2, "little" if little else "big")
    stripped = _patched(plain_library, tmp_path / "stripped.cti", shnum_at, zero)
    assert producer_problem(stripped) == (
        f"{NOT_A_PRODUCER} (it exports none of the GenTL functions GCInitLib, TLOpen, ...)")
    # a real producer without section headers still passes (TLSimu needs its library beside it)
    prod = tmp_path / "tlsimu"
    prod.mkdir()
    for f in tlsimu_cti.parent.iterdir():
        if f.suffix in (".so", ".cti"):
            shutil.copy(f, prod / f.name)
    shnum_at = 0x3C if tlsimu_cti.read_bytes()[4] == 2 else 0x30
    _patched(tlsimu_cti, prod / "TLSimu.cti", shnum_at, zero)
    assert producer_problem(prod / "TLSimu.cti") is None


def test_a_library_with_some_gentl_functions_names_the_missing_ones(tmp_path: Path) -> None:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler to build a partial producer")
    src = tmp_path / "partial.c"
    src.write_text("int GCInitLib(void) { return 0; }\nint TLOpen(void **h) { return 0; }\n")
    lib = tmp_path / "partial.cti"
    subprocess.run([cc, "-shared", "-fPIC", "-o", str(lib), str(src)], check=True, timeout=60)
    why = producer_problem(lib)
    from drivers.genicam import GENTL_REQUIRED_FUNCTIONS

    n = len(GENTL_REQUIRED_FUNCTIONS) - 2
    assert why == ("is not a complete GenTL producer (it does not export GCCloseLib, "
                   f"GCGetInfo, GCReadPort, GCWritePort and {n - 4} more)")
