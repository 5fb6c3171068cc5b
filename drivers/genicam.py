"""GenICam cameras through harvesters (GenTL producers, ``*.cti`` files).

Producer discovery (:func:`find_producers`), in this order, duplicates dropped:

1. paths given by the caller (files or folders),
2. the folders in ``GENICAM_GENTL64_PATH`` (the GenTL standard variable),
3. the folders or files in ``LENSLESSCAM_GENTL_PATH`` (this project's configured paths),
4. the installed ``genicam`` package (which ships ``viky.cti``),
5. ``$XDG_CACHE_HOME/lenslesscam/gentl`` (or ``~/.cache/...``) and its sub-folders (a
   per-user folder for producers; its cameras count as demo cameras, :func:`is_demo_producer`,
   because earlier test suites downloaded ``TLSimu.cti`` there).

The tests do not find ``TLSimu.cti`` by this search: ``python .ci/fetch_tlsimu.py`` installs
it into ``<repo>/.gl/genicam-1.5.0/`` (a folder not searched here), and the tests get that
path from the ``tlsimu_cti`` fixture of ``tests/drivers/conftest.py``.

A GenTL producer is a shared library of this platform that exports the GenTL functions: a
``.cti`` file that is not one (:func:`producer_problem`, which reads an ELF file's symbol
table without loading it) is skipped with a one-line reason, or refused when it was given
explicitly. Loading such a file through harvesters would crash the process.

Device index N (``genicam:N``) counts the devices of all producers in that order.

Features are mapped to SFNC nodes where the device has them: ExposureTime, Gain, Width,
Height, OffsetX/Y, BinningHorizontal/Vertical, PixelFormat, SensorShutterMode, TriggerDelay,
AcquisitionFrameRate, TriggerMode/TriggerSoftware; a missing node raises
:class:`~drivers.camera.FeatureNotAvailable` naming it. SFNC has no line time or readout
order: declare them from the datasheet (``line_time_us=``, ``readout_pattern=``) to get
frames with a :class:`~drivers.timing.SensorTiming`.

Settings are all or nothing: a ROI is checked against the size nodes (minimum plus a multiple
of the increment) before anything is written, and the previous ROI is written back if the
device refuses a write anyway. A PixelFormat is read back after it is set; a device that
keeps it but sends frames in another format (TLSimu: Mono16 set, Mono8 sent) is logged in
one line, and ``pixel_format``/``bit_depth`` then report the format the frames come in.

Buffers are copied before they are re-queued, and every fetch has a timeout. A buffer the
producer marks incomplete, or one with fewer values than its size, is a
:class:`~drivers.camera.FrameError` (live view counts and skips it, a snap or an acquisition
raises it); harvesters' own ``fetch`` discarded incomplete ones silently. With a software
trigger the acquisition stays armed between snaps (starting and stopping a GenTL stream can
be slow); it is disarmed before settings that need it (size, format) and on close.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import signal
import struct
import sys
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.camera import (
    CameraBase,
    CameraError,
    CameraTimeout,
    Capabilities,
    Feature,
    FeatureNotAvailable,
    Frame,
    FrameError,
    Roi,
    TriggerMode,
    bit_depth_of,
)
from drivers.timing import ReadoutPattern, SensorTiming, ShutterMode

__all__ = [
    "DEMO_PRODUCERS",
    "GENTL_REQUIRED_FUNCTIONS",
    "GenICamCamera",
    "GenICamDeviceInfo",
    "find_producers",
    "gentl_cache_dir",
    "is_demo_producer",
    "list_genicam_devices",
    "producer_problem",
]

_log = logging.getLogger(__name__)

_MONO_FORMATS = ("Mono8", "Mono10", "Mono12", "Mono14", "Mono16")
_SHUTTER_FROM_SFNC = {
    "Global": ShutterMode.GLOBAL,
    "GlobalReset": ShutterMode.GLOBAL,
    "Rolling": ShutterMode.ROLLING,
}
_SFNC_FROM_SHUTTER = {ShutterMode.GLOBAL: "Global", ShutterMode.ROLLING: "Rolling"}


# --------------------------------------------------------------------------------------------
# discovery


def gentl_cache_dir() -> Path:
    """Per-user folder searched for GenTL producers (``$XDG_CACHE_HOME/lenslesscam/gentl``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "lenslesscam" / "gentl"


def _cti_in(path: Path, depth: int = 1) -> Iterator[Path]:
    if path.is_file() and path.suffix == ".cti":
        yield path
    elif path.is_dir():
        for p in sorted(path.iterdir()):
            if p.is_file() and p.suffix == ".cti":
                yield p
            elif p.is_dir() and depth > 0:
                yield from _cti_in(p, depth - 1)


#: First bytes of a shared library: ELF (Linux), PE (Windows), Mach-O (32/64-bit either
#: byte order, and universal binaries), with the format's name.
_LIBRARY_MAGIC = (
    (b"\x7fELF", "ELF"),
    (b"MZ", "PE"),
    (b"\xfe\xed\xfa\xce", "Mach-O"),
    (b"\xce\xfa\xed\xfe", "Mach-O"),
    (b"\xfe\xed\xfa\xcf", "Mach-O"),
    (b"\xcf\xfa\xed\xfe", "Mach-O"),
    (b"\xca\xfe\xba\xbe", "Mach-O"),
)
_FORMAT_SYSTEMS = {"ELF": "Linux", "PE": "Windows", "Mach-O": "macOS"}

#: Functions every GenTL producer exports (mandatory since GenTL 1.0): discovery, the device
#: and its port, buffers and acquisition. A library lacking them is not a producer, and the
#: GenTL consumer in ``genicam`` calls them without checking (a process crash, no message).
GENTL_REQUIRED_FUNCTIONS = (
    "GCInitLib", "GCCloseLib", "GCGetInfo", "GCReadPort", "GCWritePort",
    "TLOpen", "TLClose", "TLUpdateInterfaceList", "TLGetNumInterfaces", "TLGetInterfaceID",
    "TLOpenInterface", "IFClose", "IFUpdateDeviceList", "IFGetNumDevices", "IFGetDeviceID",
    "IFOpenDevice", "DevClose", "DevGetPort", "DevOpenDataStream", "DSAnnounceBuffer",
    "DSQueueBuffer", "DSStartAcquisition", "DSStopAcquisition", "DSClose",
)

_warned_skips: set[tuple[Path, str]] = set()
_problem_cache: dict[tuple[str, int, int], str | None] = {}


def _native_format() -> str:
    if os.name == "nt":
        return "PE"
    return "Mach-O" if sys.platform == "darwin" else "ELF"


def producer_problem(path: str | os.PathLike[str]) -> str | None:
    """Why ``path`` cannot be a GenTL producer here (``None`` when it is one).

    A producer is a shared library of this platform's format that exports the GenTL
    functions (:data:`GENTL_REQUIRED_FUNCTIONS`; a library without them crashes the process
    when ``genicam`` loads it). An ELF file is checked by reading its header (type, word
    size and machine against this Python's) and its dynamic symbol table, without loading
    it; another native library (or an ELF file without section headers) is loaded in a
    short child process instead. The answer is cached per file (path, size, mtime).
    """
    try:
        st = os.stat(path)
        key = (os.path.realpath(path), st.st_size, st.st_mtime_ns)
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if key not in _problem_cache:
        _problem_cache[key] = _producer_problem(Path(path))
    return _problem_cache[key]


def _producer_problem(path: Path) -> str | None:
    try:
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if not head:
        return "is an empty file, not a shared library"
    fmt = next((name for magic, name in _LIBRARY_MAGIC if head.startswith(magic)), None)
    if fmt is None:
        return f"is not a shared library (ELF, PE or Mach-O; it starts with {head[:4]!r})"
    native = _native_format()
    if fmt != native:
        return f"is a library for {_FORMAT_SYSTEMS[fmt]} ({fmt}), not for this platform ({native})"
    if fmt == "ELF":
        try:
            exported = _elf_exports(path, GENTL_REQUIRED_FUNCTIONS)
        except _ElfProblem as exc:
            return str(exc)
        except (OSError, struct.error, IndexError, ValueError) as exc:
            return f"is a damaged ELF file ({exc})"
        if exported is not None:
            return _missing_functions(set(GENTL_REQUIRED_FUNCTIONS) - exported)
    return _exports_by_loading(path, GENTL_REQUIRED_FUNCTIONS)


def _missing_functions(missing: Iterable[str]) -> str | None:
    gone = [n for n in GENTL_REQUIRED_FUNCTIONS if n in set(missing)]
    if not gone:
        return None
    if len(gone) == len(GENTL_REQUIRED_FUNCTIONS):
        return ("is a shared library but not a GenTL producer (it exports none of the GenTL "
                "functions GCInitLib, TLOpen, ...)")
    shown = ", ".join(gone[:4]) + (f" and {len(gone) - 4} more" if len(gone) > 4 else "")
    return f"is not a complete GenTL producer (it does not export {shown})"


class _ElfProblem(Exception):
    """An ELF file that cannot be this process's shared library (message: the reason)."""


_ELF_TYPES = {1: "a relocatable object (.o)", 2: "an executable", 4: "a core dump"}
_own_elf: tuple[int, int, int] | bool | None = False  # (class, data, machine); False: unread


def _elf_ident(head: bytes) -> tuple[int, int, int, int]:
    """(class, data, type, machine) of an ELF header."""
    ei_class, ei_data = head[4], head[5]
    if ei_class not in (1, 2) or ei_data not in (1, 2):
        raise _ElfProblem(f"is a damaged ELF file (class {ei_class}, data {ei_data})")
    e_type, e_machine = struct.unpack_from("<HH" if ei_data == 1 else ">HH", head, 16)
    return ei_class, ei_data, e_type, e_machine


def _own_elf_ident() -> tuple[int, int, int] | None:
    """Word size, byte order and machine of this Python (None when it is not ELF)."""
    global _own_elf
    if _own_elf is False:
        try:
            with open(sys.executable, "rb") as f:
                head = f.read(20)
            c, d, _, m = _elf_ident(head) if head.startswith(b"\x7fELF") else (0, 0, 0, 0)
            _own_elf = (c, d, m) if c else None
        except (OSError, _ElfProblem, struct.error):
            _own_elf = None
    return _own_elf if isinstance(_own_elf, tuple) else None


def _elf_exports(path: Path, wanted: Iterable[str]) -> set[str] | None:
    """Which of ``wanted`` the ELF shared library at ``path`` exports (its dynamic symbols).

    ``None`` when the file has no section headers (stripped of them; the caller loads it in
    a child process instead). Raises :class:`_ElfProblem` for a file this process cannot load.
    """
    names = {n.encode() for n in wanted}
    with open(path, "rb") as f:
        head = f.read(64)
        ei_class, ei_data, e_type, e_machine = _elf_ident(head)
        if e_type != 3:  # ET_DYN
            what = _ELF_TYPES.get(e_type, f"an ELF file of type {e_type}")
            raise _ElfProblem(f"is {what}, not a shared library")
        own = _own_elf_ident()
        if own is not None and own != (ei_class, ei_data, e_machine):
            bits = {1: "32", 2: "64"}
            raise _ElfProblem(
                f"is a {bits[ei_class]}-bit library for ELF machine {e_machine}; this Python "
                f"is {bits[own[0]]}-bit for machine {own[2]}"
            )
        end = "<" if ei_data == 1 else ">"
        if ei_class == 2:
            shoff, = struct.unpack_from(end + "Q", head, 0x28)
            shentsize, shnum = struct.unpack_from(end + "HH", head, 0x3A)
            sh_fmt, sym_fmt = end + "IIQQQQIIQQ", end + "IBBHQQ"
        else:
            shoff, = struct.unpack_from(end + "I", head, 0x20)
            shentsize, shnum = struct.unpack_from(end + "HH", head, 0x2E)
            sh_fmt, sym_fmt = end + "IIIIIIIIII", end + "IIIBBH"
        if shoff == 0 or shnum == 0:
            return None
        f.seek(shoff)
        table = f.read(shentsize * shnum)
        if len(table) < shentsize * shnum or shentsize < struct.calcsize(sh_fmt):
            raise _ElfProblem("is a truncated or damaged ELF file (section headers)")
        sections = [struct.unpack_from(sh_fmt, table, i * shentsize) for i in range(shnum)]

        # a section header: (name, type, flags, addr, offset, size, link, info, align, entsize)
        def read(sec: tuple[int, ...]) -> bytes:
            off, size = sec[4], sec[5]
            f.seek(off)
            data = f.read(size)
            if len(data) < size:
                raise _ElfProblem("is a truncated ELF file")
            return data

        found: set[str] = set()
        sym_size = struct.calcsize(sym_fmt)
        for sec in sections:
            if sec[1] != 11:  # SHT_DYNSYM
                continue
            symbols, strings = read(sec), read(sections[sec[6]])
            for sym in struct.iter_unpack(sym_fmt, symbols[: len(symbols) // sym_size * sym_size]):
                if ei_class == 2:
                    st_name, st_info, st_other, st_shndx = sym[0], sym[1], sym[2], sym[3]
                else:
                    st_name, st_info, st_other, st_shndx = sym[0], sym[3], sym[4], sym[5]
                if st_shndx == 0 or (st_info >> 4) == 0 or (st_other & 3) in (1, 2):
                    continue  # undefined, local, or hidden: not exported
                stop = strings.find(b"\0", st_name)
                name = strings[st_name:stop if stop >= 0 else None]
                if name in names:
                    found.add(name.decode())
        return found


_LOAD_CHECK = """\
import ctypes, json, os, sys
try:
    lib = ctypes.CDLL(sys.argv[1])
except OSError as exc:
    out = {"error": str(exc)}
else:
    out = {"missing": [n for n in sys.argv[2:] if not hasattr(lib, n)]}
sys.stdout.write(json.dumps(out))
sys.stdout.flush()
os._exit(0)  # no library destructors: only the answer counts
"""


def _exports_by_loading(path: Path, wanted: Sequence[str], timeout_s: float = 20.0) -> str | None:
    """Check the exports by loading the library in a child process (it may crash there)."""
    import json
    import subprocess

    cmd = [sys.executable, "-I", "-c", _LOAD_CHECK, str(path), *wanted]
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        return f"did not finish loading within {timeout_s:g} s (checked in a child process)"
    except OSError as exc:
        return f"could not be checked ({exc.strerror or exc})"
    if run.returncode < 0:
        return f"crashes the process that loads it (signal {-run.returncode})"
    try:
        out = json.loads(run.stdout)
    except ValueError:
        last = (run.stderr.strip().splitlines() or ["no output"])[-1]
        return f"could not be checked (loading it failed: {last})"
    if "error" in out:
        return f"cannot be loaded ({out['error']})"
    return _missing_functions(out["missing"])


def find_producers(
    extra: Iterable[str | os.PathLike[str]] = (),
    *,
    use_environment: bool = True,
    include_cache: bool = True,
    include_package: bool = True,
    skipped: list[str] | None = None,
) -> list[Path]:
    """GenTL producer files (``*.cti``) found in the places listed in the module docstring.

    A path in ``extra`` is the user's explicit choice: one that does not exist, that is
    neither a ``.cti`` file nor a folder holding one, or that is not a GenTL producer
    (:func:`producer_problem`; for a folder: none of its ``.cti`` files is) raises
    ``FileNotFoundError`` naming it (the places searched by default are skipped quietly
    when empty). Any other ``.cti`` file that is not a GenTL producer is skipped: its
    one-line reason goes to ``skipped`` when given, else to the log (once per file).
    """
    candidates: list[Path] = [Path(p) for p in extra]
    for c in candidates:
        if not c.exists():
            raise FileNotFoundError(f"GenTL producer {str(c)!r} does not exist")
        ctis = list(_cti_in(c))
        if not ctis:
            what = "folder holds no .cti file" if c.is_dir() else "file is not a .cti producer"
            raise FileNotFoundError(f"GenTL producer {str(c)!r}: the {what}")
        problems = [(p, producer_problem(p)) for p in ctis]
        if all(why is not None for _, why in problems):
            if c.is_dir():
                whys = "; ".join(f"{p.name} {why}" for p, why in problems)
                raise FileNotFoundError(
                    f"GenTL producer {str(c)!r}: the folder holds no usable producer ({whys})")
            raise FileNotFoundError(f"GenTL producer {str(c)!r} {problems[0][1]}")
    if use_environment:
        for var in ("GENICAM_GENTL64_PATH", "LENSLESSCAM_GENTL_PATH"):
            candidates += [Path(p) for p in os.environ.get(var, "").split(os.pathsep) if p]
    if include_package:
        try:
            import importlib.util

            spec = importlib.util.find_spec("genicam")
            if spec is not None and spec.origin:
                candidates.append(Path(spec.origin).parent)
        except (ImportError, ValueError):
            pass
    if include_cache:
        candidates.append(gentl_cache_dir())
    found: list[Path] = []
    seen: set[Path] = set()
    for c in candidates:
        for cti in _cti_in(c):
            key = cti.resolve()
            if key in seen:
                continue
            seen.add(key)
            why = producer_problem(cti)
            if why is None:
                found.append(cti)
                continue
            line = f"GenTL producer {cti} skipped: it {why}"
            if skipped is not None:
                skipped.append(line)
            elif (key, why) not in _warned_skips:  # device lists are refreshed; say it once
                _warned_skips.add((key, why))
                _log.warning("%s", line)
    return found


#: File names of GenTL producers that ship demo cameras, not hardware.
DEMO_PRODUCERS = frozenset({"viky.cti", "TLSimu.cti"})


def is_demo_producer(path: str | os.PathLike[str]) -> bool:
    """A demo producer (:data:`DEMO_PRODUCERS`) or one in :func:`gentl_cache_dir`.

    (Earlier test suites downloaded ``TLSimu.cti`` into that folder; the tests now take it
    from ``<repo>/.gl/``, see the module docstring.)
    """
    p = Path(path)
    if p.name in DEMO_PRODUCERS:
        return True
    try:
        return p.resolve().is_relative_to(gentl_cache_dir().resolve())
    except OSError:
        return False


@dataclass(frozen=True)
class GenICamDeviceInfo:
    """One device as enumerated by the producers (``index`` is N of ``genicam:N``)."""

    index: int
    producer: str
    device_id: str
    vendor: str
    model: str
    serial_number: str
    display_name: str

    @property
    def spec(self) -> str:
        """Camera spec for :func:`drivers.open_camera`."""
        return f"genicam:{self.index}"


@contextlib.contextmanager
def _keep_sigint() -> Iterator[None]:
    """Undo the SIGINT handler harvesters installs when created in the main thread."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _harvester(producers: Sequence[Path]) -> Any:
    """A harvester with ``producers`` loaded.

    One that is not a GenTL producer (:func:`producer_problem`) is refused before it is
    loaded: loading it would crash the process.
    """
    for p in producers:
        why = producer_problem(p)
        if why is not None:
            raise CameraError(f"GenTL producer {p} {why}")
    from harvesters.core import Harvester

    with _keep_sigint():
        h = Harvester()
        try:
            for p in producers:
                h.add_file(str(p), check_existence=True)
            h.update()
        except Exception:
            h.reset()
            raise
    return h


def _device_producers(h: Any) -> list[str]:
    """Producer file of each device of a harvester (``DeviceInfo.parent.parent`` = system)."""
    names: list[str] = []
    for info in h.device_info_list:
        try:
            names.append(str(info.parent.parent.path_name))
        except Exception:
            names.append("")
    return names


def _info_str(info: Any, attr: str) -> str:
    try:
        v = getattr(info, attr)
    except Exception:
        return ""
    return "" if v is None else str(v)


def list_genicam_devices(
    producers: Sequence[str | os.PathLike[str]] | None = None,
) -> list[GenICamDeviceInfo]:
    """Devices of the given producers (default: :func:`find_producers`)."""
    paths = find_producers() if producers is None else [Path(p) for p in producers]
    if not paths:
        return []
    h = _harvester(paths)
    try:
        owners = _device_producers(h)
        return [
            GenICamDeviceInfo(
                index=i,
                producer=owners[i],
                device_id=_info_str(d, "id_"),
                vendor=_info_str(d, "vendor"),
                model=_info_str(d, "model"),
                serial_number=_info_str(d, "serial_number"),
                display_name=_info_str(d, "display_name"),
            )
            for i, d in enumerate(h.device_info_list)
        ]
    finally:
        h.reset()


# --------------------------------------------------------------------------------------------
# the camera


def _incomplete_buffer_counter() -> Any:
    """A ``harvesters.core.Callback`` counting INCOMPLETE_BUFFER events in ``count``.

    harvesters calls ``emit`` in the fetching thread for each buffer it discards.
    """
    from harvesters.core import Callback

    class IncompleteBuffers(Callback):  # type: ignore[misc]
        count = 0

        def emit(self, context: object | None = None) -> None:
            self.count += 1

    return IncompleteBuffers()


class GenICamCamera(CameraBase):
    """A GenICam device through a GenTL producer.

    ``index`` counts devices over ``producers`` (default: :func:`find_producers`; or give
    one ``producer``). ``line_time_us`` and ``readout_pattern`` declare the sensor timing
    from the datasheet (SFNC has no node for them).
    """

    backend = "genicam"

    def __init__(
        self,
        index: int = 0,
        *,
        producer: str | os.PathLike[str] | None = None,
        producers: Sequence[str | os.PathLike[str]] | None = None,
        line_time_us: float | None = None,
        readout_pattern: ReadoutPattern | str | None = None,
        num_buffers: int = 8,
        poll_s: float = 0.05,
    ) -> None:
        if producer is not None and producers is not None:
            raise ValueError("give producer or producers, not both")
        if int(index) != index or index < 0:
            raise ValueError(f"device index must be an integer >= 0, got {index!r}")
        super().__init__(f"genicam:{index}")
        if producer is not None:
            self._producers = [Path(producer)]
        elif producers is not None:
            self._producers = [Path(p) for p in producers]
        else:
            self._producers = find_producers()
        self._index = int(index)
        self._warned_nodes: set[tuple[str, str]] = set()
        if line_time_us is not None and not (math.isfinite(line_time_us) and line_time_us > 0):
            raise ValueError(f"line_time_us must be > 0, got {line_time_us!r}")
        self._line_time_decl = line_time_us
        self._pattern_decl = None if readout_pattern is None else ReadoutPattern(readout_pattern)
        self._num_buffers = int(num_buffers)
        self._poll_s = float(poll_s)
        self._h: Any = None
        self._ia: Any = None
        self._incomplete: Any = None  # INCOMPLETE_BUFFER events of the open acquirer
        self._nm: Any = None
        self._armed = False
        self._trigger_pending = False
        self._trigger_mode = TriggerMode.FREE_RUN
        self._last_id: int | None = None
        self._id_base: int | None = None
        self._model = ""
        self._display = ""
        #: (PixelFormat set, format the frames came in) once a frame showed they differ
        self._format_mismatch: tuple[str, str] | None = None

    def describe(self) -> str:
        """Device description for messages."""
        name = f" ({self._display})" if self._display else ""
        return f"genicam camera {self._index}{name}"

    # -- lifetime ------------------------------------------------------------------------------

    def _open(self) -> None:
        self._format_mismatch = None
        if not self._producers:
            raise CameraError(
                "no GenTL producer found (set GENICAM_GENTL64_PATH or LENSLESSCAM_GENTL_PATH)"
            )
        h = _harvester(self._producers)
        try:
            n = len(h.device_info_list)
            if self._index >= n:
                raise CameraError(
                    f"no GenICam device {self._index}: the producers "
                    f"{[p.name for p in self._producers]} list {n} device(s)"
                )
            info = h.device_info_list[self._index]
            self._display = _info_str(info, "display_name")
            self._model = _info_str(info, "model")
            serial = _info_str(info, "serial_number")
            self._camera_id = f"{self._model or 'genicam'}:{serial or self._index}"
            with _keep_sigint():
                ia = h.create(self._index)
        except CameraError:
            h.reset()
            raise
        except Exception as exc:
            h.reset()
            raise CameraError(f"cannot open {self.describe()}: {exc}") from exc
        self._h, self._ia = h, ia
        self._nm = ia.remote_device.node_map
        self._incomplete = _incomplete_buffer_counter()
        ia.add_callback(type(ia).Events.INCOMPLETE_BUFFER, self._incomplete)
        try:
            ia.num_buffers = max(self._num_buffers, ia.min_num_buffers)
            self._init_device()
        except Exception as exc:
            self._close()
            raise CameraError(f"cannot set up {self.describe()}: {exc}") from exc

    def _init_device(self) -> None:
        pf = self._node("PixelFormat")
        if pf is not None and self._readable(pf) and pf.value not in _MONO_FORMATS:
            for name in _MONO_FORMATS:
                if name in self._enum_values(pf):
                    pf.value = name
                    break
        if self._node("TriggerSelector") is not None:
            self._try_node_write("TriggerSelector", "FrameStart", "frame-start trigger")
        if self._node("TriggerMode") is not None:
            self._nm.TriggerMode.value = "Off"
        self._trigger_mode = TriggerMode.FREE_RUN

    def _close(self) -> None:
        try:
            self._disarm()
        finally:
            ia, h = self._ia, self._h
            self._ia = self._h = self._nm = None
            try:
                if ia is not None:
                    ia.destroy()
            finally:
                if h is not None:
                    h.reset()

    # -- node helpers --------------------------------------------------------------------------

    def _node(self, name: str) -> Any | None:
        nm = self._nm
        if nm is None:
            raise CameraError(f"{self.describe()} is not open")
        try:
            if not nm.has_node(name):
                return None
            node = getattr(nm, name)
            mode = int(node.node.get_access_mode())
        except Exception:
            return None
        return node if mode >= 2 else None  # WO, RO or RW: implemented and available

    @staticmethod
    def _readable(node: Any) -> bool:
        return int(node.node.get_access_mode()) in (3, 4)

    @staticmethod
    def _writable(node: Any) -> bool:
        return int(node.node.get_access_mode()) in (2, 4)

    @staticmethod
    def _enum_values(node: Any) -> list[str]:
        try:
            return [e.symbolic for e in node.entries if int(e.node.get_access_mode()) >= 3]
        except Exception:
            return list(node.symbolics)

    def _require(self, feature: Feature, name: str, *, write: bool = False) -> Any:
        node = self._node(name)
        if node is None:
            raise self._unavailable(feature, f"the device has no '{name}' node")
        if write and not self._writable(node):
            raise self._unavailable(feature, f"'{name}' is not writable now")
        if not write and not self._readable(node):
            raise self._unavailable(feature, f"'{name}' is not readable now")
        return node

    def _get(self, feature: Feature, name: str) -> Any:
        with self._lock:
            return self._require(feature, name).value

    def _set(self, feature: Feature, name: str, value: Any) -> None:
        import genicam.genapi as genapi

        with self._lock:
            node = self._require(feature, name, write=True)
            try:
                node.value = value
            except (genapi.OutOfRangeException, genapi.InvalidArgumentException) as exc:
                raise ValueError(f"{self.describe()}: {name} = {value!r} rejected: {exc}") from exc
            except genapi.GenericException as exc:
                raise CameraError(f"{self.describe()}: setting {name} failed: {exc}") from exc

    def _has(self, name: str, write: bool = True) -> bool:
        node = self._node(name)
        return node is not None and (self._writable(node) if write else self._readable(node))

    # -- capabilities --------------------------------------------------------------------------

    def capabilities(self) -> Capabilities:
        """Features present on this device (writable SFNC nodes)."""
        self._require_open()
        with self._lock:
            feats: set[Feature] = set()
            table = {
                Feature.EXPOSURE: ("ExposureTime",),
                Feature.GAIN: ("Gain",),
                Feature.ROI: ("Width", "Height"),
                Feature.BINNING: ("BinningHorizontal", "BinningVertical"),
                Feature.PIXEL_FORMAT: ("PixelFormat",),
                Feature.SHUTTER_MODE: ("SensorShutterMode",),
                Feature.TRIGGER_DELAY: ("TriggerDelay",),
                Feature.TRIGGER_SOFTWARE: ("TriggerMode", "TriggerSoftware"),
                Feature.FRAME_RATE: ("AcquisitionFrameRate",),
            }
            for feat, names in table.items():
                if all(self._has(n) for n in names):
                    feats.add(feat)
            w = self._node("Width")
            hgt = self._node("Height")
            bin_ = self.binning
            size = self._sensor_shape()
            if size is not None:
                sh, sw = size
            else:  # only the Width/Height maxima, with an offset set: the best we know
                sw = self._int_or(("SensorWidth", "WidthMax"), w.max if w is not None else 0)
                sh = self._int_or(("SensorHeight", "HeightMax"), hgt.max if hgt is not None else 0)
            pf = self._node("PixelFormat")
            formats = tuple(
                f for f in (self._enum_values(pf) if pf is not None else []) if f in _MONO_FORMATS
            )
            modes: tuple[TriggerMode, ...] = (TriggerMode.FREE_RUN,)
            if Feature.TRIGGER_SOFTWARE in feats:
                modes = (TriggerMode.FREE_RUN, TriggerMode.SOFTWARE)
            shutter: tuple[ShutterMode, ...] = ()
            ssm = self._node("SensorShutterMode")
            if ssm is not None:
                shutter = tuple(
                    dict.fromkeys(
                        _SHUTTER_FROM_SFNC[v]
                        for v in self._enum_values(ssm)
                        if v in _SHUTTER_FROM_SFNC
                    )
                )
            return Capabilities(
                backend=self.backend,
                camera_id=self.camera_id,
                model=self._model,
                sensor_width=int(sw),
                sensor_height=int(sh),
                features=frozenset(feats),
                pixel_formats=formats,
                trigger_modes=modes,
                shutter_modes=shutter,
                readout_patterns=() if self._pattern_decl is None else (self._pattern_decl,),
                exposure_range_us=self._range("ExposureTime"),
                gain_range=self._range("Gain"),
                frame_rate_range_hz=self._range("AcquisitionFrameRate"),
                binning_factors=self._binnings(),
                # the size nodes count binned pixels; a Roi counts unbinned ones
                roi_min_size=(int(w.min) * bin_ if w is not None else bin_,
                              int(hgt.min) * bin_ if hgt is not None else bin_),
                roi_step=(self._inc(w) * bin_, self._inc(hgt) * bin_),
            )

    def _sensor_shape(self) -> tuple[int, int] | None:
        """(rows, columns) of the whole sensor in unbinned pixels; None where unreliable.

        SFNC ``SensorHeight``/``SensorWidth`` count unbinned pixels; ``HeightMax``/``WidthMax``
        and the maxima of ``Height``/``Width`` count binned ones (scaled back here). The
        ``Height``/``Width`` maxima shrink with the offset on many devices, so they are used
        only while ``OffsetY``/``OffsetX`` are 0. A few node reads, until one gives a size.
        """
        with self._lock:
            binning = self.binning
            size: list[int] = []
            for sensor, most, dim, offset in (("SensorHeight", "HeightMax", "Height", "OffsetY"),
                                              ("SensorWidth", "WidthMax", "Width", "OffsetX")):
                n = self._int_or((sensor,), 0)
                if n <= 0:
                    n = self._int_or((most,), 0)
                    if n <= 0:
                        node = self._node(dim)
                        if node is None or self._int_or((offset,), 0) != 0:
                            return None
                        n = int(node.max)
                    n *= binning
                if n <= 0:
                    return None
                size.append(n)
            return size[0], size[1]

    def _int_or(self, names: Sequence[str], default: int) -> int:
        for n in names:
            node = self._node(n)
            if node is not None and self._readable(node):
                return int(node.value)
        return int(default)

    def _range(self, name: str) -> tuple[float, float] | None:
        node = self._node(name)
        if node is None:
            return None
        try:
            return (float(node.min), float(node.max))
        except Exception:
            return None

    @staticmethod
    def _inc(node: Any) -> int:
        if node is None:
            return 1
        try:
            return max(1, int(node.inc))
        except Exception:
            return 1

    def _binnings(self) -> tuple[int, ...]:
        node = self._node("BinningHorizontal")
        if node is None:
            return (1,)
        try:
            return tuple(range(int(node.min), int(node.max) + 1))
        except Exception:
            return (1,)

    # -- features ------------------------------------------------------------------------------

    def _get_exposure_us(self) -> float:
        """SFNC ExposureTime (microseconds)."""
        return float(self._get(Feature.EXPOSURE, "ExposureTime"))

    def _try_node_write(self, node: str, value: Any, purpose: str) -> None:
        """Best-effort write of a helper node; a refusal is logged once with its reason.

        Devices differ in which helper nodes (auto modes, enables, selectors) are writable;
        the main write that follows reports the real failure if the helper mattered.
        """
        try:
            getattr(self._nm, node).value = value
        except Exception as exc:  # genicam raises its own exception types for refused writes
            key = (node, str(value))
            if key not in self._warned_nodes:
                self._warned_nodes.add(key)
                _log.warning(
                    "%s: could not set %s=%r for %s: %s", self.describe(), node, value, purpose, exc
                )

    def _do_set_exposure_us(self, value: float) -> None:
        with self._lock:
            if self._has("ExposureAuto"):
                self._try_node_write("ExposureAuto", "Off", "a manual exposure")
            self._set(Feature.EXPOSURE, "ExposureTime", float(value))

    def _get_gain(self) -> float:
        """SFNC Gain (device units, usually dB)."""
        return float(self._get(Feature.GAIN, "Gain"))

    def _do_set_gain(self, value: float) -> None:
        with self._lock:
            if self._has("GainAuto"):
                self._try_node_write("GainAuto", "Off", "a manual gain")
            self._set(Feature.GAIN, "Gain", float(value))

    def _get_binning(self) -> int:
        """SFNC BinningHorizontal (1 without binning nodes)."""
        with self._lock:
            node = self._node("BinningHorizontal")
            return 1 if node is None or not self._readable(node) else int(node.value)

    def _do_set_binning(self, value: int) -> None:
        self._require_idle("change binning")
        with self._lock:
            if value == 1 and self._node("BinningHorizontal") is None:
                return
            self._disarm()
            self._set(Feature.BINNING, "BinningHorizontal", int(value))
            self._set(Feature.BINNING, "BinningVertical", int(value))

    def _get_roi(self) -> Roi:
        """Width/Height/OffsetX/OffsetY (in unbinned pixels)."""
        with self._lock:
            b = self.binning
            w = int(self._get(Feature.ROI, "Width"))
            h = int(self._get(Feature.ROI, "Height"))
            ox = self._node("OffsetX")
            oy = self._node("OffsetY")
            x = int(ox.value) if ox is not None and self._readable(ox) else 0
            y = int(oy.value) if oy is not None and self._readable(oy) else 0
            return Roi(x * b, y * b, w * b, h * b)

    def _do_set_roi(self, value: Roi) -> None:
        """Check the whole ROI against the size nodes, then write it; all or nothing.

        A value off the nodes' grid (minimum + a multiple of the increment, in binned
        pixels) is refused before anything is written; a write the device refuses anyway
        restores the previous ROI.
        """
        self._require_idle("change the ROI")
        with self._lock:
            self._disarm()  # size nodes are not writable while the acquisition is armed
            self._require(Feature.ROI, "Width", write=True)
            self._require(Feature.ROI, "Height", write=True)
            b = self.binning
            if value.x and not self._has("OffsetX"):
                raise self._unavailable(Feature.ROI, "no writable 'OffsetX': ROI x must be 0")
            if value.y and not self._has("OffsetY"):
                raise self._unavailable(Feature.ROI, "no writable 'OffsetY': ROI y must be 0")
            target = self._roi_node_values(value, b)
            previous = {
                n: int(node.value)
                for n in ("Width", "Height", "OffsetX", "OffsetY")
                if (node := self._node(n)) is not None and self._readable(node)
            }
            try:
                self._write_roi_nodes(target)
            except Exception as exc:
                try:
                    self._write_roi_nodes(previous)
                except Exception as again:
                    raise CameraError(
                        f"{exc}; restoring the previous ROI failed too ({again}); "
                        f"the ROI is now {self._optional(lambda: self.roi)}"
                    ) from exc
                raise

    def _roi_node_values(self, value: Roi, binning: int) -> dict[str, int]:
        """Node values (binned pixels) for ``value``; ValueError naming the first bad one."""
        dev = self.describe()
        parts = (("x", "OffsetX", value.x), ("y", "OffsetY", value.y),
                 ("width", "Width", value.width), ("height", "Height", value.height))
        out: dict[str, int] = {}
        for label, name, v in parts:
            if v % binning:
                raise ValueError(
                    f"{dev}: ROI {label} {v} is not a multiple of the binning {binning}; "
                    "nothing was changed"
                )
            n = v // binning
            node = self._node(name)
            if node is None:  # only an offset of 0 gets here (checked above)
                continue
            try:
                lo, inc = int(node.min), self._inc(node)
            except Exception:  # no usable min/inc: the write itself decides
                out[name] = n
                continue
            if n < lo:
                raise ValueError(
                    f"{dev}: ROI {label} {v} is below the minimum {lo * binning} ({name}); "
                    "nothing was changed"
                )
            if (n - lo) % inc:
                below = lo + (n - lo) // inc * inc
                raise ValueError(
                    f"{dev}: ROI {label} {v} rejected: {name} takes {lo * binning} plus a "
                    f"multiple of {inc * binning} (e.g. {below * binning} or "
                    f"{(below + inc) * binning}); nothing was changed"
                )
            out[name] = n
        return out

    def _write_roi_nodes(self, values: dict[str, int]) -> None:
        """Offsets to 0 first (so a larger size fits), then the size, then the offsets."""
        for off in ("OffsetX", "OffsetY"):
            if self._has(off):
                self._set(Feature.ROI, off, 0)
        for name in ("Width", "Height"):
            if name in values:
                self._set(Feature.ROI, name, values[name])
        for off in ("OffsetX", "OffsetY"):
            if values.get(off):
                self._set(Feature.ROI, off, values[off])

    def _get_pixel_format(self) -> str:
        """SFNC PixelFormat, or the format the frames come in once one showed it differs.

        A device may accept a PixelFormat and keep sending another one (TLSimu takes Mono16
        and sends Mono8): after such a frame this reports what the device really delivers.
        """
        value = str(self._get(Feature.PIXEL_FORMAT, "PixelFormat"))
        seen = self._format_mismatch
        return seen[1] if seen is not None and seen[0] == value else value

    def _do_set_pixel_format(self, value: str) -> None:
        self._require_idle("change the pixel format")
        if value not in _MONO_FORMATS:
            raise ValueError(f"pixel format {value!r} not supported; use one of {_MONO_FORMATS}")
        with self._lock:
            self._disarm()  # PixelFormat is not writable while the acquisition is armed
            node = self._require(Feature.PIXEL_FORMAT, "PixelFormat", write=True)
            if value not in self._enum_values(node):
                raise ValueError(
                    f"{self.describe()}: pixel format {value!r} not offered "
                    f"(device offers {self._enum_values(node)})"
                )
            self._format_mismatch = None  # the next frame shows whether the device follows
            self._set(Feature.PIXEL_FORMAT, "PixelFormat", value)
            now = str(self._get(Feature.PIXEL_FORMAT, "PixelFormat"))
            if now != value:
                raise CameraError(
                    f"{self.describe()}: PixelFormat = {value!r} was accepted but the device "
                    f"reads back {now!r}; it stays at {now}"
                )

    @property
    def bit_depth(self) -> int:
        """Bits of the current pixel format."""
        return bit_depth_of(self.pixel_format)

    def _get_shutter_mode(self) -> ShutterMode:
        """SFNC SensorShutterMode (Global, GlobalReset -> global; Rolling)."""
        v = str(self._get(Feature.SHUTTER_MODE, "SensorShutterMode"))
        if v not in _SHUTTER_FROM_SFNC:
            raise CameraError(f"{self.describe()}: unknown SensorShutterMode {v!r}")
        mode = _SHUTTER_FROM_SFNC[v]
        if mode is ShutterMode.ROLLING and self._pattern_decl in (
            ReadoutPattern.OUTSIDE_IN,
            ReadoutPattern.CENTRE_OUT,
        ):
            return ShutterMode.DUAL_ROLLING
        return mode

    def _do_set_shutter_mode(self, value: ShutterMode) -> None:
        mode = ShutterMode(value)
        if mode is ShutterMode.DUAL_ROLLING:
            raise self._unavailable(
                Feature.SHUTTER_MODE, "SFNC has no dual rolling shutter (vendor feature)"
            )
        self._set(Feature.SHUTTER_MODE, "SensorShutterMode", _SFNC_FROM_SHUTTER[mode])

    def _get_readout_pattern(self) -> ReadoutPattern:
        """Declared readout pattern (``readout_pattern=`` at construction)."""
        if self._pattern_decl is None:
            raise self._unavailable(
                Feature.READOUT_PATTERN, "not in SFNC; declare readout_pattern= from the datasheet"
            )
        return self._pattern_decl

    def _do_set_readout_pattern(self, value: ReadoutPattern) -> None:
        raise self._unavailable(Feature.READOUT_PATTERN, "a property of the sensor, not settable")

    def _get_line_time_us(self) -> float:
        """Declared line time (``line_time_us=`` at construction)."""
        if self._line_time_decl is None:
            raise self._unavailable(
                Feature.LINE_TIME, "not in SFNC; declare line_time_us= from the datasheet"
            )
        return self._line_time_decl

    def _do_set_line_time_us(self, value: float) -> None:
        raise self._unavailable(Feature.LINE_TIME, "a property of the sensor, not settable")

    def _get_trigger_delay_us(self) -> float:
        """SFNC TriggerDelay (microseconds)."""
        return float(self._get(Feature.TRIGGER_DELAY, "TriggerDelay"))

    def _do_set_trigger_delay_us(self, value: float) -> None:
        self._set(Feature.TRIGGER_DELAY, "TriggerDelay", float(value))

    def _get_trigger_mode(self) -> TriggerMode:
        """Free-run (TriggerMode Off) or software (TriggerMode On, TriggerSource Software)."""
        return self._trigger_mode

    def _do_set_trigger_mode(self, value: TriggerMode) -> None:
        mode = TriggerMode(value)
        self._require_idle("change the trigger mode")
        with self._lock:
            if mode is TriggerMode.SOFTWARE:
                self._require(Feature.TRIGGER_SOFTWARE, "TriggerSoftware", write=True)
                self._require(Feature.TRIGGER_SOFTWARE, "TriggerMode", write=True)
            elif self._node("TriggerMode") is None:
                self._trigger_mode = mode
                return
            self._disarm()
            if mode is TriggerMode.SOFTWARE and self._has("TriggerSource"):
                self._set(Feature.TRIGGER_SOFTWARE, "TriggerSource", "Software")
            self._set(
                Feature.TRIGGER_SOFTWARE,
                "TriggerMode",
                "On" if mode is TriggerMode.SOFTWARE else "Off",
            )
            self._trigger_mode = mode

    def _get_frame_rate_hz(self) -> float:
        """SFNC AcquisitionFrameRate."""
        return float(self._get(Feature.FRAME_RATE, "AcquisitionFrameRate"))

    @property
    def resulting_frame_rate_hz(self) -> float | None:
        """The device's SFNC AcquisitionResultingFrameRate (or ResultingFrameRate).

        Where it has neither, the rate the frame timing allows (:class:`CameraBase`).
        """
        for name in ("AcquisitionResultingFrameRate", "ResultingFrameRate"):
            if self._has(name, write=False):
                try:
                    with self._lock:
                        return float(self._node(name).value)  # type: ignore[union-attr]
                except Exception as exc:  # a device error: fall back to the timing
                    _log.debug("%s: reading %s: %s", self.describe(), name, exc)
        return super().resulting_frame_rate_hz

    def _do_set_frame_rate_hz(self, value: float) -> None:
        with self._lock:
            if self._has("AcquisitionFrameRateEnable"):
                self._try_node_write("AcquisitionFrameRateEnable", True, "a paced frame rate")
            self._set(Feature.FRAME_RATE, "AcquisitionFrameRate", float(value))

    @property
    def timing(self) -> SensorTiming | None:
        """Timing from the declared line time/pattern and ExposureTime, else None."""
        if self._line_time_decl is None or self._pattern_decl is None:
            return None
        try:
            exposure = self.exposure_us
            delay = self._optional(lambda: self.trigger_delay_us) or 0.0
            with self._lock:
                height = self._require(Feature.ROI, "Height")
                rows = self._int_or(("SensorHeight", "HeightMax"), int(height.max))
        except FeatureNotAvailable:
            return None
        return SensorTiming.from_exposure_us(
            rows, self._line_time_decl, exposure, self._pattern_decl, delay
        )

    # -- acquisition ---------------------------------------------------------------------------

    def _arm(self) -> None:
        if not self._armed:
            self._ia.start()
            self._armed = True
            self._trigger_pending = False
            self._id_base = None  # devices may restart their frame counter

    def _disarm(self) -> None:
        if self._armed and self._ia is not None:
            self._armed = False
            self._trigger_pending = False
            self._ia.stop()

    def _fetch(self, timeout_s: float) -> Frame:
        """One buffer, copied before it is re-queued; CameraTimeout after ``timeout_s``.

        A buffer the producer marks incomplete (harvesters discards and re-queues it, then
        emits INCOMPLETE_BUFFER) is a :class:`~drivers.camera.FrameError`: live view counts and
        skips it, an acquisition ends there. harvesters' ``fetch`` would wait on for the next
        buffer and hide the loss; ``try_fetch`` returns None, and the count tells which.
        """
        before = self._incomplete.count
        fetched = self._ia.try_fetch(timeout=timeout_s)
        if fetched is None:
            if self._incomplete.count > before:
                raise FrameError(f"{self.describe()}: the device delivered an incomplete buffer "
                                 "(the frame is lost)")
            raise CameraTimeout(f"{self.describe()}: no frame within {timeout_s:.3g} s")
        with fetched as buffer:  # re-queued on leaving
            comp = buffer.payload.components[0]
            fmt = str(comp.data_format)
            w, h = int(comp.width), int(comp.height)
            if fmt not in _MONO_FORMATS:
                raise CameraError(f"{self.describe()}: delivered unsupported format {fmt}")
            data = comp.data
            if data.size != h * w:  # a buffer cut short (or padded): not this frame
                raise FrameError(
                    f"{self.describe()}: delivered {data.size} pixel values for a "
                    f"{h}x{w} frame (an incomplete or damaged buffer)")
            pixels = data.reshape(h, w).copy()  # owned: the buffer goes back
            device_id = int(buffer.frame_id)
            extra: dict[str, Any] = {"device_frame_id": device_id, "model": self._model}
            try:
                extra["device_timestamp_ns"] = int(buffer.timestamp_ns)
            except Exception as exc:  # optional buffer info some producers lack
                _log.debug("%s: no buffer timestamp (%s)", self.describe(), exc)
        frame_id = self._frame_id_of(device_id)
        self._check_delivered_format(fmt, extra)
        return self._make_frame(pixels, frame_id, pixel_format=fmt, extra=extra)

    def _check_delivered_format(self, fmt: str, extra: dict[str, Any]) -> None:
        """Note a frame whose format is not the PixelFormat set (a warning, once per setting).

        The frame says what it is (``pixel_format``, its dtype); ``extra`` keeps the format
        that was asked for, and :attr:`pixel_format` and :attr:`bit_depth` report the
        delivered one from then on.
        """
        try:
            requested = str(self._get(Feature.PIXEL_FORMAT, "PixelFormat"))
        except FeatureNotAvailable:
            return
        if fmt == requested:
            self._format_mismatch = None
            return
        extra["requested_pixel_format"] = requested
        if self._format_mismatch != (requested, fmt):
            self._format_mismatch = (requested, fmt)
            _log.warning(
                "%s: PixelFormat is %s but the device delivers %s frames (it ignores the "
                "setting); frames, pixel_format and bit_depth say %s",
                self.describe(), requested, fmt, fmt,
            )

    def _frame_id_of(self, device_id: int) -> int:
        """Frame id: the device's id shifted so ids keep increasing across acquisitions.

        Within one acquisition a gap in the device's ids stays a gap (a lost frame shows).
        """
        if self._id_base is None:
            self._id_base = 0 if self._last_id is None else self._last_id + 1 - device_id
        frame_id = device_id + self._id_base
        self._last_id = frame_id
        return frame_id

    def _trigger(self) -> None:
        self._nm.TriggerSoftware.execute()
        self._trigger_pending = True

    def _snap(self, timeout_s: float) -> Frame:
        with self._lock:
            self._arm()
            try:
                if self._trigger_mode is TriggerMode.SOFTWARE:
                    self._trigger()
                    frame = self._fetch(timeout_s)
                    self._trigger_pending = False
                    return frame
                return self._fetch(timeout_s)
            except BaseException:
                self._disarm()
                raise
            finally:
                if self._trigger_mode is TriggerMode.FREE_RUN:
                    self._disarm()

    def _stream_begin(self) -> None:
        self._arm()

    def _stream_grab(self, poll_s: float) -> Frame | None:
        with self._lock:
            if self._trigger_mode is TriggerMode.SOFTWARE and not self._trigger_pending:
                self._trigger()
            try:
                frame = self._fetch(min(poll_s, self._poll_s))
            except CameraTimeout:
                return None
            self._trigger_pending = False
            return frame

    def _stream_end(self) -> None:
        if self._trigger_mode is TriggerMode.FREE_RUN or self._trigger_pending:
            self._disarm()

    # -- white-box helpers for tests -------------------------------------------------------------

    def _fetch_untriggered(self, timeout_s: float) -> Frame:
        """Fetch without triggering (tests: a software-triggered device times out)."""
        with self._lock:
            self._arm()
            try:
                return self._fetch(timeout_s)
            except CameraTimeout:
                self._disarm()
                raise
