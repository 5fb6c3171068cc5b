"""Install step for the driver tests' second GenTL producer (run once, at install time).

``TLSimu.cti`` (a simulated GenTL camera) ships only in the ``genicam==1.5.0`` wheel, and
installing that version would replace the 1.6.0 the project uses. This script downloads the
wheel from the package index (install time is the only time anything is downloaded) and
extracts the producer and its one library into ``<repo>/.gl/genicam-1.5.0/`` (git-ignored),
where ``tests/drivers/conftest.py`` finds it. The test session itself never downloads: without
this folder the TLSimu tests skip and say to run this script. Usage: ``python .ci/fetch_tlsimu.py``.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DEST = REPO / ".gl" / "genicam-1.5.0"
FILES = ("TLSimu.cti", "libVirtualFG.so")


def main() -> int:
    """Download and extract TLSimu.cti unless it is already there."""
    if all((DEST / f).exists() for f in FILES):
        print(f"TLSimu producer already in {DEST}")
        return 0
    with tempfile.TemporaryDirectory() as d:
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:"]
        cmd += ["--disable-pip-version-check", "-q", "genicam==1.5.0", "-d", d]
        subprocess.run(cmd, check=True, timeout=600)
        wheels = sorted(Path(d).glob("genicam-1.5.0-*.whl"))
        if not wheels:
            print(f"pip download left no genicam 1.5.0 wheel in {d}", file=sys.stderr)
            return 1
        DEST.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".tlsimu-", dir=DEST.parent))
        try:
            with zipfile.ZipFile(wheels[0]) as zf:
                for name in zf.namelist():
                    base = name.rsplit("/", 1)[-1]
                    if base in FILES:
                        (tmp / base).write_bytes(zf.read(name))
            missing = [f for f in FILES if not (tmp / f).exists()]
            if missing:
                print(f"{wheels[0].name} lacks {missing}", file=sys.stderr)
                return 1
            shutil.rmtree(DEST, ignore_errors=True)
            tmp.rename(DEST)  # atomic: the folder appears complete or not at all
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"TLSimu producer installed in {DEST}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
