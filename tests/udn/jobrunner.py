"""Run ``lenslesscam`` commands in real processes with test-only fault hooks (never imported
by production code).

Two ways to use it:

- ``python -m tests.udn.jobrunner jobs run SPEC --out RUN``: one command, hooks from the
  environment (below);
- :class:`JobServer`: a long-lived process that imports torch and the app once, then forks a
  fresh child per command. A child is a real process (it can be SIGKILLed at any moment) that
  starts in milliseconds instead of the seconds an interpreter needs to import torch on a busy
  machine. :meth:`JobServer.spawn` starts the GUI's job processes this way (the
  ``spawn`` argument of :class:`app.gui.jobs_core.JobQueue`).

Hooks (environment variables of the command):

- ``LENSLESSCAM_TEST_STALL_AT=N``: after iteration N has been recorded, the job sleeps until it
  is killed (a kill at a known iteration);
- ``LENSLESSCAM_TEST_CKPT_PAUSE=STAGE:NTH``: at the NTH checkpoint write of the session the job
  touches ``$LENSLESSCAM_TEST_MARK`` and sleeps until it is killed, at STAGE: ``write`` (half
  the temporary file written), ``rotate`` (file written and verified, hash recorded, before the
  newest checkpoint becomes the previous one) or ``replace`` (after that, before the new file
  takes the name ``checkpoint.pt``).
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
STALL_ENV = "LENSLESSCAM_TEST_STALL_AT"
PAUSE_ENV = "LENSLESSCAM_TEST_CKPT_PAUSE"
MARK_ENV = "LENSLESSCAM_TEST_MARK"


def _stall_forever(mark: str | None) -> None:
    if mark:
        Path(mark).write_text(str(os.getpid()))
    while True:
        time.sleep(0.05)


def install_hooks() -> None:
    """Wrap the job's functions according to the environment (see the module docstring)."""
    from recon.udn import jobs, rundir

    stall = os.environ.get(STALL_ENV)
    if stall:
        at = int(stall)
        record = jobs._Job._progress_record

        def progress_record(self: Any, s: Any) -> None:
            if s.iteration == at + 1:  # iteration `at` has been written in full
                _stall_forever(os.environ.get(MARK_ENV))
            record(self, s)

        jobs._Job._progress_record = progress_record  # type: ignore[method-assign]

    pause = os.environ.get(PAUSE_ENV)
    if pause:
        stage, nth_text = pause.split(":")
        nth = int(nth_text)
        mark = os.environ.get(MARK_ENV)
        count = {"n": 0}
        write_bytes, rotate = rundir._write_bytes, rundir._rotate

        def slow_write(fh: Any, data: bytes) -> None:
            count["n"] += 1
            if stage == "write" and count["n"] == nth:
                fh.write(data[: len(data) // 2])
                fh.flush()
                _stall_forever(mark)
            write_bytes(fh, data)

        def slow_rotate(rd: Path) -> None:
            if stage == "rotate" and count["n"] == nth:
                _stall_forever(mark)
            rotate(rd)
            if stage == "replace" and count["n"] == nth:
                _stall_forever(mark)

        rundir._write_bytes = slow_write  # type: ignore[assignment]
        rundir._rotate = slow_rotate  # type: ignore[assignment]


def run_cli(argv: list[str]) -> int:
    """``lenslesscam ARGV`` with the hooks of the environment installed."""
    import torch

    torch.set_num_threads(1)
    install_hooks()
    from app.cli import main

    return main(argv)


# --------------------------------------------------------------------------------------------
# The fork server
# --------------------------------------------------------------------------------------------


def _serve() -> None:
    """Read JSON requests from stdin, answer on stdout (one line each)."""
    # everything a job imports, once, before any fork (no torch operation runs here)
    import PIL.Image
    import PIL.PngImagePlugin
    import tifffile
    import torch
    import torch._dynamo  # torch.optim imports it lazily: seconds on a busy machine
    import torch.optim

    import app.cli
    import app.commands.jobs
    import recon.io
    import recon.metrics
    import recon.models
    import recon.udn.jobs  # noqa: F401

    del PIL, tifffile, torch

    app.cli.build_parser()  # imports every command module
    out = sys.stdout
    for line in sys.stdin:
        req = json.loads(line)
        if "argv" in req:
            pid = os.fork()
            if pid == 0:  # the child: a fresh process for one command
                rc = 1
                try:
                    fd = os.open(req["log"], os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
                    os.dup2(fd, 1)
                    os.dup2(fd, 2)
                    os.environ.update(req.get("env") or {})
                    if req.get("cwd"):
                        os.chdir(req["cwd"])
                    signal.signal(signal.SIGTERM, signal.SIG_DFL)
                    rc = run_cli(req["argv"])
                except SystemExit as exc:
                    rc = exc.code if isinstance(exc.code, int) else 1
                except BaseException:
                    import traceback

                    traceback.print_exc()
                finally:
                    with contextlib.suppress(Exception):
                        sys.stdout.flush()
                        sys.stderr.flush()
                    os._exit(rc)
            out.write(json.dumps({"pid": pid}) + "\n")
        elif "wait" in req:
            _, status = os.waitpid(int(req["wait"]), 0)
            out.write(json.dumps({"rc": os.waitstatus_to_exitcode(status)}) + "\n")
        elif "poll" in req:  # reap without blocking: rc None while the child runs
            done, status = os.waitpid(int(req["poll"]), os.WNOHANG)
            rc = os.waitstatus_to_exitcode(status) if done else None
            out.write(json.dumps({"rc": rc}) + "\n")
        out.flush()


class JobServer:
    """Client of :func:`_serve`: ``start(argv, env) -> pid``, ``wait(pid) -> return code``."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ)
        env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
        env["OMP_NUM_THREADS"] = "1"
        self.proc = subprocess.Popen([sys.executable, "-m", "tests.udn.jobrunner", "--serve"],
                                     cwd=REPO, env=env, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        self.n = 0
        self.pending: set[int] = set()

    def _ask(self, req: dict[str, Any], timeout: float = 120.0) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps(req) + "\n")
        self.proc.stdin.flush()
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        assert ready, f"the job server did not answer {req} in {timeout} s"
        answer: dict[str, Any] = json.loads(self.proc.stdout.readline())
        return answer

    def start(self, argv: list[str], env: dict[str, str] | None = None,
              log: Path | None = None, cwd: Path | None = None) -> tuple[int, Path]:
        """Fork a child running ``lenslesscam ARGV``; its pid and its log (stdout + stderr,
        appended; default a new file in ``log_dir``)."""
        self.n += 1
        log = log or self.log_dir / f"child_{self.n:03d}.log"
        pid = int(self._ask({"argv": [str(a) for a in argv], "env": env or {},
                             "log": str(log), "cwd": str(cwd) if cwd else None})["pid"])
        self.pending.add(pid)
        return pid, log

    def poll(self, pid: int) -> int | None:
        """A child's exit code (reaped), or None while it runs."""
        rc = self._ask({"poll": pid})["rc"]
        if rc is not None:
            self.pending.discard(pid)
        return None if rc is None else int(rc)

    def spawn(self, args: list[str], cwd: Path, env: dict[str, str],
              log: Any) -> ServerChild:
        """:data:`app.gui.jobs_core.Spawner`: ``lenslesscam ARGS`` in a forked child."""
        log.flush()
        pid, _ = self.start(args, env, Path(log.name), cwd)
        return ServerChild(self, pid)

    def wait(self, pid: int, timeout: float = 120.0) -> int:
        """Reap a child: its exit code, or minus the signal that ended it."""
        rc = int(self._ask({"wait": pid}, timeout)["rc"])
        self.pending.discard(pid)
        return rc

    def kill(self, pid: int) -> int:
        """SIGKILL a child and reap it."""
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
        return self.wait(pid)

    def close(self) -> None:
        """End the server, killing the children still running (a test that failed)."""
        for pid in list(self.pending):
            with contextlib.suppress(Exception):
                self.kill(pid)
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()

    def __enter__(self) -> JobServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ServerChild:
    """A child of :class:`JobServer` with Popen's ``pid``/``poll``/``wait``/``terminate``/
    ``kill``."""

    def __init__(self, server: JobServer, pid: int) -> None:
        self.server, self.pid = server, pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self.server.poll(self.pid)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            if deadline is not None and time.monotonic() > deadline:
                raise subprocess.TimeoutExpired(f"child {self.pid}", timeout or 0.0)
            time.sleep(0.05)
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


if __name__ == "__main__":
    if sys.argv[1:] == ["--serve"]:
        _serve()
    else:
        sys.exit(run_cli(sys.argv[1:]))
