"""UDN jobs panel: create a job from the current measurement, queue it, watch it, open results.

The panel is a view of the jobs folder (:mod:`app.gui.jobs_core`): a timer polls the
:class:`~app.gui.jobs_core.JobQueue` (which also starts queued jobs, one per device) and shows
each job's state, a progress bar with ETA, its loss curve and latest preview. Jobs run in their
own processes, so closing the window leaves them running; a new window finds them again.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QEvent, QItemSelectionModel, Qt, QTimer, QUrl, Signal
from PySide6.QtGui import QAction, QDesktopServices
from PySide6.QtWidgets import (
    QApplication,
    QCheckBox,
    QComboBox,
    QDialog,
    QDialogButtonBox,
    QFormLayout,
    QFrame,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QLineEdit,
    QMenu,
    QPlainTextEdit,
    QProgressBar,
    QPushButton,
    QScrollArea,
    QSizePolicy,
    QSplitter,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.gui.image_view import ImagePanel
from app.gui.jobs_core import (
    RUN_DIR,
    AppJobState,
    JobQueue,
    JobView,
    Spawner,
    cancel_job,
    combine_jobs,
    combine_refusal,
    create_job,
    estimate_job_memory,
    jobs_dir_problem,
    queue_resume,
    read_loss,
    spawn_job_process,
)
from app.gui.widgets import (
    ComboBox,
    DoubleSpinBox,
    ElidedLabel,
    SciSpinBox,
    SpinBox,
    never_wider,
)
from app.gui.workers import TaskQueue

__all__ = ["JobsPanel", "Measurement", "NewJobDialog", "ResultDialog"]

_log = logging.getLogger(__name__)

_COLUMNS = ("Job", "Device", "State", "Progress", "ETA", "Iteration", "Loss")


@dataclass(frozen=True)
class Measurement:
    """What a new job (or a trade) starts from: the newest frame and the preview's PSF.

    ``dark``: the preview's dark level (None: auto, the camera's black level or the frame's
    1st percentile: ``preview_engine.frame_dark_level``).
    """

    frame: Any
    psf: Any
    psf_source: str = ""
    psf_path: str = ""
    dark: float | None = None


def _fmt_bytes(n: float | None) -> str:
    if n is None:
        return "unknown"
    from recon.udn.memory import format_bytes

    return format_bytes(n)


class NewJobDialog(QDialog):
    """Settings of a new UDN job with a live memory estimate."""

    def __init__(self, sensor: tuple[int, int], source: str, parent: QWidget | None = None,
                 name: str = "udn", *, hashes: dict[str, str] | None = None,
                 suggestion_dirs: list[Path] | None = None,
                 run_planner: Callable[[Callable[[], bool]], Any] | None = None,
                 save_dir: Path | None = None) -> None:
        """A dialog for a ``sensor``-sized measurement described by ``source``.

        ``hashes``: :func:`recon.suggest.input_hashes` of the measurement and PSF; plans and
        trades for them are looked for in ``suggestion_dirs``. ``run_planner(cancelled)`` makes
        a plan (run off the GUI thread; it may stop early once ``cancelled()`` is True, and its
        plan is then discarded); it is saved in ``save_dir`` with the hashes.
        """
        super().__init__(parent)
        self._hashes = hashes
        self._suggestion_dirs = list(suggestion_dirs or [])
        self._run_planner = run_planner
        self._planner_cancel = threading.Event()
        self._save_dir = save_dir
        self._planner_queue: TaskQueue | None = None
        self.suggestions_found: list[Any] = []
        #: job-spec settings of the applied suggestion that no control shows (its recorded
        #: UDN settings, recon.suggest.Suggestion.spec): sections() passes them to the job
        self.suggested_sections: dict[str, dict[str, Any]] = {}
        self.setWindowTitle("New UDN job")
        self.sensor = sensor
        from recon.udn.spec import SCHEMA

        def default(section: str, key: str) -> Any:
            return SCHEMA[section][key].default

        self.name = QLineEdit(name)
        self.downsample = SpinBox()
        self.downsample.setRange(1, 64)
        self.downsample.setValue(2)
        self.downsample.setToolTip("Box downsampling of frame and PSF (the job's [data] "
                                   "downsample; 2 here for a live full-sensor frame, a spec's "
                                   "default is 1); the memory estimate follows it")
        self.max_iter = SpinBox()
        self.max_iter.setRange(1, 10_000_000)
        self.max_iter.setValue(int(default("stopping", "max_iter")))
        self.time_limit = DoubleSpinBox()
        self.time_limit.setDecimals(3)  # 0.001 h = 3.6 s (two decimals made 0.004 h "none")
        self.time_limit.setRange(0.0, 240.0)
        self.time_limit.setSingleStep(0.25)
        self.time_limit.setSuffix(" h")
        self.time_limit.setSpecialValueText("none")
        self.scales = SpinBox()
        self.scales.setRange(1, 8)
        self.scales.setValue(int(default("network", "scales")))
        self.channels = SpinBox()
        self.channels.setRange(1, 512)
        self.channels.setValue(int(default("network", "channels")))
        self.lr = SciSpinBox()  # typed as 1e-3 too
        self.lr.setRange(1e-5, 0.1)
        self.lr.setSingleStep(0.001)
        self.lr.setValue(float(default("optimizer", "lr")))
        self.lr.setToolTip(SCHEMA["optimizer"]["lr"].help)
        self.tv_weight = SciSpinBox()  # 1e-7 is not 0
        self.tv_weight.setRange(0.0, 1.0)
        self.tv_weight.setSingleStep(1e-4)
        self.tv_weight.setValue(float(default("optimizer", "tv_weight")))
        self.tv_weight.setToolTip(SCHEMA["optimizer"]["tv_weight"].help)
        self.headroom = DoubleSpinBox()
        self.headroom.setDecimals(2)
        self.headroom.setRange(0.1, 10.0)
        self.headroom.setSingleStep(0.1)
        self.headroom.setValue(float(default("optimizer", "headroom")))
        self.headroom.setToolTip("Output gain: the least-squares gain times this factor "
                                 "(> 1 leaves room for highlights; "
                                 + SCHEMA["optimizer"]["headroom"].help + ")")
        self.holdout = DoubleSpinBox()
        self.holdout.setDecimals(3)
        self.holdout.setRange(0.0, 0.5)
        self.holdout.setSingleStep(0.01)
        self.holdout.setValue(float(default("stopping", "holdout")))
        self.holdout.setToolTip(SCHEMA["stopping"]["holdout"].help)
        self.patience = SpinBox()
        self.patience.setRange(1, 10_000_000)
        self.patience.setValue(int(default("stopping", "patience")))
        self.patience.setToolTip(SCHEMA["stopping"]["patience"].help)
        self.seeds = SpinBox()
        self.seeds.setRange(1, 16)
        self.seeds.setValue(1)
        self.seeds.setToolTip("Queue this many jobs with seeds 0, 1, ...; select them when they "
                              "have finished and press Combine for their average (an ensemble: "
                              "better where the data say least, e.g. many erased pixels)")
        self.device = ComboBox()
        self.device.addItems(["auto", "cpu"])
        try:
            import torch

            for i in range(torch.cuda.device_count()):
                self.device.addItem(f"cuda:{i}")
        except Exception:  # no torch CUDA: CPU only
            pass
        self.device.setCurrentText(str(default("device", "device")))
        self.threads = SpinBox()
        from recon.threads import max_requested_threads

        # more than 4 per core is refused when the job starts (256 was offered, then failed)
        self.threads.setRange(0, max_requested_threads())
        self.threads.setValue(int(default("device", "threads")))
        self.threads.setSpecialValueText("auto (free cores)")
        self.precision = ComboBox()
        self.precision.addItems(list(SCHEMA["device"]["precision"].choices or ("float32",)))
        self.precision.setCurrentText(str(default("device", "precision")))
        self.checkpoint_every = SpinBox()
        self.checkpoint_every.setRange(1, 1_000_000)
        self.checkpoint_every.setValue(int(default("output", "checkpoint_every")))
        self.preview_every = SpinBox()
        self.preview_every.setRange(0, 1_000_000)
        self.preview_every.setValue(int(default("output", "preview_every")))
        self.with_fista = QCheckBox("also average with FISTA-TV (with_fista.tif)")
        self.with_fista.setChecked(bool(default("output", "with_fista")))
        self.with_fista.setToolTip(
            "When the run ends, average its mean estimate half and half with FISTA-TV at the "
            "automatic tau: the best result measured without ground truth on the real "
            "DiffuserCam pairs (docs/udn.md); seconds to a minute more.")
        self.memory = QLabel("")
        self.memory.setWordWrap(True)
        self.suggestion_box = ComboBox()
        self.suggestion_box.setToolTip("UDN settings found by lenslesscam plan or trade for "
                                       "this measurement and PSF (their recorded input hashes)")
        self.suggestion_box.setSizeAdjustPolicy(
            QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
        self.suggestion_box.setMinimumContentsLength(24)  # long labels: full text in the list
        self.apply_suggestion_button = QPushButton("Apply")
        self.plan_button = QPushButton("Run planner")
        self.plan_button.setToolTip("Plan this measurement (seconds); the plan is saved and "
                                    "offered here")
        self.suggestion_note = never_wider(QLabel(""))
        self.suggestion_note.setWordWrap(True)
        srow = QHBoxLayout()
        srow.setContentsMargins(0, 0, 0, 0)
        srow.addWidget(self.suggestion_box, 1)
        srow.addWidget(self.apply_suggestion_button)
        srow.addWidget(self.plan_button)
        self.setMinimumWidth(560)  # room for a suggestion's values (1366x768 screens: fine)
        form = QFormLayout(self)
        form.addRow(QLabel(source))
        form.addRow("Suggested settings", srow)
        form.addRow("", self.suggestion_note)
        form.addRow("Name", self.name)
        form.addRow("Downsampling", self.downsample)
        form.addRow("Iterations", self.max_iter)
        form.addRow("Time limit", self.time_limit)
        form.addRow("Network scales", self.scales)
        form.addRow("Channels", self.channels)
        form.addRow("Learning rate", self.lr)
        form.addRow("TV weight", self.tv_weight)
        form.addRow("Gain headroom", self.headroom)
        form.addRow("Held-out fraction", self.holdout)
        form.addRow("Patience", self.patience)
        form.addRow("Seeds (ensemble)", self.seeds)
        form.addRow("Device", self.device)
        form.addRow("CPU threads", self.threads)
        form.addRow("Precision", self.precision)
        # two intervals on one row: the dialog fits a 1366x768 screen with the row below
        outs = QHBoxLayout()
        outs.addWidget(QLabel("checkpoint"))
        outs.addWidget(self.checkpoint_every, 1)
        outs.addWidget(QLabel("preview"))
        outs.addWidget(self.preview_every, 1)
        form.addRow("Every (iterations)", outs)
        form.addRow("At the end", self.with_fista)
        form.addRow("Memory", self.memory)
        self.buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok
                                        | QDialogButtonBox.StandardButton.Cancel)
        self.buttons.button(QDialogButtonBox.StandardButton.Ok).setText("Queue job")
        self.buttons.accepted.connect(self.accept)
        self.buttons.rejected.connect(self.reject)
        #: why the job could not run with these settings (None: it can be queued)
        self.refusal: str | None = None
        form.addRow(self.buttons)
        for w in (self.downsample, self.scales, self.channels):
            w.valueChanged.connect(self.update_estimate)
        self.device.currentIndexChanged.connect(self.update_estimate)
        self.precision.currentIndexChanged.connect(self.update_estimate)
        self.apply_suggestion_button.clicked.connect(self.apply_selected_suggestion)
        self.suggestion_box.currentIndexChanged.connect(
            lambda i: self.suggestion_box.setToolTip(self.suggestion_box.itemText(i)))
        self.plan_button.clicked.connect(self.run_planner)
        self.update_estimate()
        self.refresh_suggestions()

    # -- suggestions ---------------------------------------------------------------------------

    def refresh_suggestions(self) -> None:
        """Look for plans and trades made for this measurement (or its PSF); list them."""
        from recon.suggest import find_suggestions

        found = ([] if self._hashes is None else
                 find_suggestions(self._suggestion_dirs, self._hashes, tuple(self.sensor)))
        self.suggestions_found = found
        self.suggestion_box.clear()
        for s in found:
            self.suggestion_box.addItem(s.label)
            self.suggestion_box.setItemData(self.suggestion_box.count() - 1,
                                            f"{s.path}\n{s.detail}",
                                            Qt.ItemDataRole.ToolTipRole)
        has = bool(found)
        self.suggestion_box.setEnabled(has)
        self.apply_suggestion_button.setEnabled(has)
        can_plan = (self._run_planner is not None and self._save_dir is not None
                    and self._hashes is not None)
        self.plan_button.setEnabled(can_plan and self._planner_queue is None)
        if not has:
            self.suggestion_box.addItem("none for this measurement")
            self._note("no plan or trade found for this measurement"
                       + (": Run planner to make one" if can_plan else ""))
        else:
            other = sum(not s.same_measurement for s in found)
            parts = ([f"{len(found) - other} for this measurement"] if other < len(found)
                     else [])
            parts += [f"{other} made on another frame with this PSF"] if other else []
            self._note(f"{' and '.join(parts)}: choose one and Apply")

    def _note(self, text: str, tip: str | None = None) -> None:
        self.suggestion_note.setText(text)
        self.suggestion_note.setToolTip(text if tip is None else f"{text}\n{tip}")

    def apply_selected_suggestion(self) -> None:
        """Fill the fields from the chosen suggestion (they stay editable)."""
        i = self.suggestion_box.currentIndex()
        if not 0 <= i < len(self.suggestions_found):
            return
        self.apply_suggestion(self.suggestions_found[i])

    def apply_suggestion(self, s: Any) -> None:
        """Set the fields a :class:`recon.suggest.Suggestion` names; say where they came from."""
        v = s.settings
        if "downsample" in v:
            self.downsample.setValue(int(v["downsample"]))
        if "max_iter" in v:
            self.max_iter.setValue(int(v["max_iter"]))
        if "time_limit_s" in v:
            self.time_limit.setValue(float(v["time_limit_s"]) / 3600.0)
        if "scales" in v:
            self.scales.setValue(int(v["scales"]))
        if "channels" in v:
            self.channels.setValue(int(v["channels"]))
        if "lr" in v:
            self.lr.setValue(float(v["lr"]))
        if "precision" in v and self.precision.findText(str(v["precision"])) >= 0:
            self.precision.setCurrentText(str(v["precision"]))
        hidden, changed = self._apply_spec(getattr(s, "spec", None) or {})
        self.suggested_sections = hidden
        names = ", ".join(f"{k}={val}" for k, val in v.items())
        n_hidden = sum(len(keys) for keys in hidden.values())
        text = f"applied {s.origin}"
        if n_hidden:
            text += f"; {n_hidden} more recorded UDN settings go to the job (not shown here)"
        if changed:
            text += f"; the dialog cannot take {', '.join(changed)}"
        if getattr(s, "not_carried", ()):
            text += f"; not carried: {', '.join(s.not_carried)}"
        more = "; ".join(f"{sec}.{k}={val}" for sec, keys in hidden.items()
                         for k, val in keys.items())
        self._note(text, f"{s.path}\n{s.detail}\n{names}" + (f"\nto the job: {more}"
                                                            if more else ""))
        self.update_estimate()

    def _apply_spec(self, spec: dict[str, dict[str, Any]]
                    ) -> tuple[dict[str, dict[str, Any]], list[str]]:
        """Set the controls that show a suggestion's spec settings; return the others.

        Also returns the values a control could not take (outside its range, or finer than
        its steps): the control shows, and the job gets, what it was set to.
        """
        controls: dict[tuple[str, str], Any] = {
            ("network", "scales"): self.scales, ("network", "channels"): self.channels,
            ("optimizer", "lr"): self.lr, ("optimizer", "tv_weight"): self.tv_weight,
            ("optimizer", "headroom"): self.headroom, ("stopping", "holdout"): self.holdout,
            ("stopping", "patience"): self.patience}
        hidden: dict[str, dict[str, Any]] = {}
        changed: list[str] = []
        for section, keys in spec.items():
            for key, val in keys.items():
                w = controls.get((section, key))
                if (section, key) == ("device", "precision"):
                    if self.precision.findText(str(val)) >= 0:
                        self.precision.setCurrentText(str(val))
                    else:
                        changed.append(f"precision {val}")
                elif w is None:
                    hidden.setdefault(section, {})[key] = val
                else:
                    w.setValue(val)
                    if abs(float(w.value()) - float(val)) > 1e-9 * max(abs(float(val)), 1e-12):
                        changed.append(f"{key} {val} (set to {w.value():g})")
        return hidden, changed

    def run_planner(self) -> None:
        """Plan this measurement off the GUI thread; the saved plan is then offered."""
        if self._run_planner is None or self._save_dir is None or self._hashes is None:
            return
        if self._planner_queue is not None:
            return
        from recon.suggest import write_plan_suggestion

        planner, folder, hashes = self._run_planner, self._save_dir, dict(self._hashes)
        cancelled = self._planner_cancel = threading.Event()

        def work() -> Path:
            plan = planner(cancelled.is_set)
            if cancelled.is_set():  # the dialog closed: a search cut short is not a plan
                raise RuntimeError("planner cancelled")
            return write_plan_suggestion(folder, plan, hashes)

        self._planner_queue = TaskQueue("planner", self)
        self.plan_button.setEnabled(False)
        self._note("planning this measurement…")
        self._planner_queue.submit(work, name="plan", on_done=self._planned,
                                   on_error=self._plan_failed)

    def _end_planner(self, wait: bool = True) -> None:
        if not wait:
            self._planner_cancel.set()  # the tau search stops at its next check
        q, self._planner_queue = self._planner_queue, None
        if q is not None and wait:
            q.shutdown()
        elif q is not None:
            q.abandon()

    def _planned(self, path: Path) -> None:
        self._end_planner()
        self.refresh_suggestions()
        for i, s in enumerate(self.suggestions_found):
            if s.path == path:
                self.suggestion_box.setCurrentIndex(i)
        self._note(f"plan saved as {path.name}: press Apply to use it", str(path))

    def _plan_failed(self, exc: BaseException) -> None:
        self._end_planner()
        self.refresh_suggestions()
        self._note(f"planner failed: {exc}")

    def remembered(self) -> dict[str, Any]:
        """The dialog's settings to offer again in the next one (:meth:`restore`)."""
        return {"downsample": int(self.downsample.value()), "seeds": int(self.seeds.value()),
                "sections": self.sections()}

    def restore(self, last: Mapping[str, Any]) -> bool:
        """Fill the controls from :meth:`remembered` of an earlier dialog; whether it did.

        Values of the wrong kind are skipped (the file it comes from may be edited); a spin
        box takes the nearest value in its range.
        """
        sec = last.get("sections") if isinstance(last, Mapping) else None
        if not isinstance(sec, Mapping):
            return False

        def get(section: str, key: str) -> Any:
            keys = sec.get(section)
            return keys.get(key) if isinstance(keys, Mapping) else None

        spins: list[tuple[Any, Any, float]] = [
            (self.downsample, last.get("downsample"), 1), (self.seeds, last.get("seeds"), 1),
            (self.max_iter, get("stopping", "max_iter"), 1),
            (self.patience, get("stopping", "patience"), 1),
            (self.holdout, get("stopping", "holdout"), 1),
            (self.time_limit, get("stopping", "time_limit_s") or 0.0, 1 / 3600.0),
            (self.scales, get("network", "scales"), 1),
            (self.channels, get("network", "channels"), 1),
            (self.lr, get("optimizer", "lr"), 1),
            (self.tv_weight, get("optimizer", "tv_weight"), 1),
            (self.headroom, get("optimizer", "headroom"), 1),
            (self.threads, get("device", "threads"), 1),
            (self.checkpoint_every, get("output", "checkpoint_every"), 1),
            (self.preview_every, get("output", "preview_every"), 1)]
        for box, value, unit in spins:
            if isinstance(value, int | float) and not isinstance(value, bool) \
                    and math.isfinite(value):
                v = value * unit
                box.setValue(round(v) if isinstance(box, SpinBox) else float(v))
        if isinstance(get("output", "with_fista"), bool):
            self.with_fista.setChecked(get("output", "with_fista"))
        for combo, key in ((self.device, "device"), (self.precision, "precision")):
            value = get("device", key)
            if isinstance(value, str) and combo.findText(value) >= 0:
                combo.setCurrentText(value)
        self._note("the settings of the last job queued (Apply a suggestion to replace them)")
        self.update_estimate()
        return True

    def done(self, r: int) -> None:
        """Close at once; a running planner is cancelled and left to end in the background.

        Waiting for it held the GUI thread for the plan's seconds (its tau search takes
        seconds at 240x320, minutes at 960x1280); cancelled, the search stops at its next
        check (between taus and FISTA iterations) and nothing is saved.
        """
        self._end_planner(wait=False)
        super().done(r)

    def sections(self) -> dict[str, dict[str, Any]]:
        """Spec sections from the controls and the applied suggestion's hidden settings.

        The applied suggestion's settings that no control shows: :attr:`suggested_sections`.
        """
        stopping: dict[str, Any] = {"max_iter": int(self.max_iter.value()),
                                    "patience": int(self.patience.value()),
                                    "holdout": float(self.holdout.value())}
        if self.time_limit.value() > 0:
            stopping["time_limit_s"] = float(self.time_limit.value()) * 3600.0
        out: dict[str, dict[str, Any]] = {
            "network": {"scales": int(self.scales.value()),
                        "channels": int(self.channels.value())},
            "optimizer": {"lr": float(self.lr.value()),
                          "tv_weight": float(self.tv_weight.value()),
                          "headroom": float(self.headroom.value())},
            "stopping": stopping,
            "device": {"device": self.device.currentText(), "threads": int(self.threads.value()),
                       "precision": self.precision.currentText()},
            "output": {"checkpoint_every": int(self.checkpoint_every.value()),
                       "preview_every": int(self.preview_every.value()),
                       "with_fista": self.with_fista.isChecked(),
                       "status_seconds": 1.0},
        }
        for section, keys in self.suggested_sections.items():  # the controls' values win
            for key, val in keys.items():
                out.setdefault(section, {}).setdefault(key, val)
        return out

    @property
    def ok_button(self) -> QPushButton:
        """*Queue job* (disabled while the job could not run)."""
        return self.buttons.button(QDialogButtonBox.StandardButton.Ok)

    @property
    def can_queue(self) -> bool:
        """Whether the settings make a job that can run (the estimate could be made)."""
        return self.refusal is None

    def keyPressEvent(self, event: Any) -> None:
        """Enter ends the edit of a box and queues nothing; Escape still closes.

        Queueing (up to 16 seeds, hours each) is a click: Enter in Iterations queued the job
        at once, with the other fields as they were (the button box makes Queue job the
        default button when it is shown).
        """
        from PySide6.QtCore import Qt

        if event.key() in (Qt.Key.Key_Return, Qt.Key.Key_Enter):
            event.accept()
            return
        super().keyPressEvent(event)

    def accept(self) -> None:
        """Queue only a job that can run (the button; Enter in the dialog queues nothing)."""
        if self.refusal is not None:
            return
        super().accept()

    def update_estimate(self) -> None:
        """Recompute the memory estimate shown; refuse to queue a job that could not run."""
        try:
            est, avail, source = estimate_job_memory(self.sensor, int(self.downsample.value()),
                                                     self.sections())
        except Exception as exc:  # shown, and the job cannot be queued
            self.refusal = f"cannot queue this job: {exc}"
            self.memory.setText(f"cannot estimate: {exc}; the job could not run")
            self.memory.setToolTip(self.refusal)
            self.memory.setStyleSheet("color: #cf222e;")
            self.estimate_bytes = None
            self.ok_button.setEnabled(False)
            self.ok_button.setToolTip(self.refusal)
            return
        self.refusal = None
        self.ok_button.setEnabled(True)
        self.ok_button.setToolTip("")
        self.estimate_bytes = est.peak_bytes
        fits = avail is None or est.peak_bytes <= avail
        h, w = self.sensor[0] // self.downsample.value(), self.sensor[1] // self.downsample.value()
        # one short line (the dialog fills a 768-pixel screen; a second line was cut off), the
        # details in the tooltip
        self.memory.setText(
            f"about {_fmt_bytes(est.peak_bytes)} of {_fmt_bytes(avail)} available"
            + ("" if fits else " – will NOT fit: fewer channels or more downsampling"))
        self.memory.setToolTip(f"{est.parameters:,} parameters, scene {h}x{w} (HxW); peak "
                               f"to expect: the estimate {_fmt_bytes(est.total_bytes)} x "
                               f"{est.peak_factor:g} (measured on {est.device_type}); "
                               f"available memory from {source}")
        self.memory.setStyleSheet("" if fits else "color: #cf222e;")


class ResultDialog(QDialog):
    """A job's result (with FISTA-TV, best, mean and final estimates) with its metadata."""

    def __init__(self, view: JobView, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        from recon.io import read_reconstruction

        self.setWindowTitle(f"Result: {view.name}")
        # within the screen's free area (1100 px ran 80 px off a 1024 px screen)
        screen = (parent.screen() if parent is not None else None) or QApplication.primaryScreen()
        avail = screen.availableGeometry() if screen is not None else None
        w, h = 1100, 600
        if avail is not None and avail.width() > 0:
            w, h = min(w, avail.width() - 20), min(h, avail.height() - 60)
        self.resize(w, h)
        outer = QVBoxLayout(self)
        lay = QHBoxLayout()
        outer.addLayout(lay, 1)
        self.panels: dict[str, ImagePanel] = {}
        self.meta: dict[str, dict[str, Any]] = {}
        for which in ("with_fista", "best", "mean", "final"):
            path = view.results.get(which)
            if path is None:
                continue
            x, meta = read_reconstruction(path)
            img = np.asarray(x[0, 0] if x.shape[1] == 1 else x[0].mean(axis=0), dtype=np.float32)
            # the best estimate's own iteration (its metadata's iterations are the run's)
            it = meta.get("best_iteration") if which == "best" else None
            label = (f"{which} (it {it} of {meta.get('iterations')})" if it is not None else
                     f"{which} ({meta.get('iterations')} it)")
            footer = f"{path.name} · {img.shape[0]}x{img.shape[1]} (HxW)"
            if which == "with_fista":  # short titles: four panels share the window's width
                f = meta.get("fista") or {}
                label = f"{meta.get('udn_estimate', 'UDN')} + FISTA-TV"
                if isinstance(f.get("tau"), int | float):
                    footer += f" · FISTA-TV tau {f['tau']:.3g}, {f.get('iterations')} it"
            if which == "mean" and meta.get("mean_count"):
                label = f"mean of {int(meta['mean_count'])} (every {meta.get('average_every')})"
            panel = ImagePanel(label)
            # the same width each, whatever the title's length (a longer one made its panel,
            # and the image, wider): widths from the stretch below, not the contents
            panel.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Preferred)
            panel.set_image(img, (0.0, float(np.percentile(img, 99.5)) or 1.0))
            panel.footer.setText(footer)
            panel.title.setToolTip(label)
            self.panels[which] = panel
            self.meta[which] = meta
            lay.addWidget(panel, 1)  # the same width each: images side by side at one scale
        if not self.panels:
            lay.addWidget(QLabel("this job has no result yet"))
        self.metadata = QPlainTextEdit(format_metadata(self.meta))
        self.metadata.setReadOnly(True)
        self.metadata.setMaximumHeight(200)
        outer.addWidget(self.metadata)


def format_metadata(meta: dict[str, dict[str, Any]]) -> str:
    """The results' metadata as indented ``key: value`` lines (nested keys indented)."""
    lines: list[str] = []

    def walk(d: Any, indent: int) -> None:
        for k, v in d.items():
            if isinstance(v, dict) and v:
                lines.append(f"{'  ' * indent}{k}:")
                walk(v, indent + 1)
            else:
                text = f"{v:.6g}" if isinstance(v, float) else str(v)
                if len(text) > 160:
                    text = text[:157] + "..."
                lines.append(f"{'  ' * indent}{k}: {text}")

    for which, m in meta.items():
        lines.append(f"[{which}]")
        walk(m, 1)
    return "\n".join(lines)


class JobsPanel(QWidget):
    """Jobs table, loss plot, latest preview, and the actions."""

    job_created = Signal(object)

    def __init__(
        self,
        jobs_dir: str | Path,
        current: Callable[[], Measurement | None],
        parent: QWidget | None = None,
        poll_ms: int = 1000,
        spawn: Spawner = spawn_job_process,
    ) -> None:
        """``current()``: the measurement and PSF a new job starts from (None: none).

        ``spawn`` starts a job's process (:class:`~app.gui.jobs_core.JobQueue`).
        """
        super().__init__(parent)
        self._current = current
        self.queue = JobQueue(jobs_dir, spawn)
        #: where the job dialog looks for plans and trades (``recon.suggest``); the first one
        #: also receives the plans the dialog makes
        self.suggestion_dirs: list[Path] = [self.queue.jobs_dir / "suggestions"]
        self.views: list[JobView] = []
        self.result_dialog: ResultDialog | None = None
        #: the settings of the last job queued (NewJobDialog.remembered), offered by the next
        #: dialog; the main window keeps them in the app's settings between sessions
        self.last_job: dict[str, Any] = {}
        self.dialog: NewJobDialog | None = None  # the open New job dialog, if any

        self.new_button = QPushButton("New job from current measurement…")
        self.cancel_button = QPushButton("Cancel")
        self.resume_button = QPushButton("Resume")
        self.open_button = QPushButton("Open results")
        self.folder_button = QPushButton("Open folder")
        # a push button with a menu: the bar's look and its width (80 px, as before), the two
        # ways to combine each enabled on its own (one job is enough with FISTA-TV)
        self.combine_button = QPushButton("Combine")
        self.combine_button.setToolTip("Combine the selected finished jobs (same measurement, "
                                       "different seeds): choose how in the menu")
        self.combine_menu = QMenu(self.combine_button)
        self.combine_menu.setToolTipsVisible(True)
        self.combine_action = QAction("Average the seeds", self.combine_menu)
        self.combine_action.setToolTip(
            "Average the best estimates of two or more selected finished jobs of one "
            "measurement (an ensemble of seeds).")
        self.combine_fista_action = QAction("Average the seeds and FISTA-TV", self.combine_menu)
        self.combine_fista_action.setToolTip(
            "Average the selected jobs' iterate means (mean.tif; their best estimates when a "
            "job has none), then half and half with FISTA-TV (automatic tau) of the same "
            "measurement: above the jobs alone and oracle-tau FISTA-TV on the real "
            "DiffuserCam pairs (docs/udn.md); seconds to a minute.")
        for a in (self.combine_action, self.combine_fista_action):
            a.setEnabled(False)
            self.combine_menu.addAction(a)
        self.combine_button.setMenu(self.combine_menu)
        #: runs a combine off the GUI thread (FISTA-TV's tau search takes up to a minute);
        #: made at the first combine, shut down by :meth:`stop`
        self._combine_queue: TaskQueue | None = None
        self._combining: str | None = None  # what the running combine is, for the message
        #: the selected job's loss curve as last read (folder, the loss file's (size, mtime),
        #: the curve): read again only when it changed, and a long one off the GUI thread (a
        #: day's loss.csv, 200k rows, took 2-3 s to read: the window froze at every poll)
        self._loss: tuple[Path, tuple[int, int], tuple[Any, ...]] | None = None
        self._loss_queue: TaskQueue | None = None
        self._loss_reading = False
        self._loss_not_before = 0.0  # monotonic time of the next background read
        for b in (self.cancel_button, self.resume_button, self.open_button,
                  self.combine_button):
            b.setEnabled(False)  # nothing is selected until the first listing
        #: why no job can be queued in the jobs folder (a file, not writable), or None
        self.folder_problem = jobs_dir_problem(jobs_dir)
        self.folder_label = QLabel(f"jobs folder: {jobs_dir}")
        self.folder_label.setToolTip(str(jobs_dir))
        never_wider(self.folder_label)
        self.folder_label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.message = _MessageLabel()
        if self.folder_problem is not None:  # said at start, not when a job fails to be written
            _log.warning("%s", self.folder_problem)
            self.message.setText(self.folder_problem)
            self.folder_label.setStyleSheet("color: #cf222e;")
        bar = QHBoxLayout()
        for b in (self.new_button, self.cancel_button, self.resume_button, self.open_button,
                  self.combine_button, self.folder_button):
            bar.addWidget(b)
        self.folder_label.setAlignment(Qt.AlignmentFlag.AlignRight
                                       | Qt.AlignmentFlag.AlignVCenter)
        bar.addWidget(self.folder_label, 1)

        self.table = QTableWidget(0, len(_COLUMNS))
        self.table.viewport().installEventFilter(self)
        self.table.setHorizontalHeaderLabels(list(_COLUMNS))
        self.table.setSelectionBehavior(QTableWidget.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QTableWidget.SelectionMode.ExtendedSelection)
        self.table.setEditTriggers(QTableWidget.EditTrigger.NoEditTriggers)
        header = self.table.horizontalHeader()
        header.setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(0, QHeaderView.ResizeMode.Stretch)  # the name gets the rest
        self.table.verticalHeader().setVisible(False)
        # rows a line of text high (the progress bars' default made them 30 px: at 1366x768
        # the panel's strip showed three jobs)
        row_h = self.table.fontMetrics().height() + 6
        self.table.verticalHeader().setMinimumSectionSize(row_h)
        self.table.verticalHeader().setDefaultSectionSize(row_h)
        self.loss_plot = pg.PlotWidget()
        self.loss_plot.setLabel("left", "log10")
        self.loss_plot.setLabel("bottom", "iteration")
        self.loss_plot.addLegend(offset=(-10, 10))
        # a day's run has 10^5 points: drawn as the peaks of what the pixels can show
        self.loss_plot.setDownsampling(auto=True, mode="peak")
        self.loss_plot.setClipToView(True)
        self.loss_curve = self.loss_plot.plot([], [], pen=pg.mkPen("c", width=2), name="loss")
        self.held_curve = self.loss_plot.plot([], [], pen=pg.mkPen("y", width=1),
                                              name="held-out")
        self.preview = ImagePanel("Latest preview")
        self.preview.autoscale_button.setVisible(False)
        self.details = QLabel("")
        self.details.setWordWrap(True)
        self.details.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)

        split = QSplitter(Qt.Orientation.Horizontal)
        left = QWidget()
        ll = QVBoxLayout(left)
        ll.setContentsMargins(0, 0, 0, 0)
        ll.addWidget(self.table, 1)
        # at most two lines of details under the table (a long detail, such as the resume
        # command of a run that was still improving, scrolls): the table keeps its rows
        self.details_area = QScrollArea()
        self.details_area.setWidget(self.details)
        self.details_area.setWidgetResizable(True)
        self.details_area.setFrameShape(QFrame.Shape.NoFrame)
        self.details_area.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.details_area.setMaximumHeight(2 * self.details.fontMetrics().lineSpacing() + 6)
        ll.addWidget(self.details_area)
        split.addWidget(left)
        split.addWidget(self.loss_plot)
        split.addWidget(self.preview)
        split.setSizes([500, 300, 250])
        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        lay.addLayout(bar)
        lay.addWidget(self.message)
        lay.addWidget(split, 1)

        self.new_button.clicked.connect(self.new_job_dialog)
        self.cancel_button.clicked.connect(self.cancel_selected)
        self.resume_button.clicked.connect(self.resume_selected)
        self.open_button.clicked.connect(self.open_selected)
        self.folder_button.clicked.connect(self.open_folder)
        self.combine_action.triggered.connect(lambda _checked=False: self.combine_selected())
        self.combine_fista_action.triggered.connect(
            lambda _checked=False: self.combine_selected(with_fista=True))
        self.table.itemSelectionChanged.connect(self._selection_changed)
        self.timer = QTimer(self)
        self.timer.setInterval(int(poll_ms))
        self.timer.timeout.connect(self.refresh)
        self.timer.start()
        self._shown_preview: Path | None = None
        self.refresh()

    # -- state ---------------------------------------------------------------------------------

    def stop(self) -> None:
        """Stop polling (the jobs themselves keep running) and the combine queue.

        A combine in progress is waited for (up to 10 s; then it finishes, and writes its
        file, in the background, and its result is not shown).
        """
        self.timer.stop()
        q, self._combine_queue = self._combine_queue, None
        self._combining = None
        if q is not None:
            q.shutdown()
        lq, self._loss_queue = self._loss_queue, None
        if lq is not None:
            lq.shutdown()

    def refresh(self) -> None:
        """Poll the queue (starts queued jobs) and update the table and the details."""
        try:
            views = self.queue.poll()
        except Exception as exc:  # a broken folder must not break the window
            self.message.setText(f"jobs folder: {exc}")
            return
        from recon.udn.jobs import format_hms

        keep = {v.folder for v in self.selected_all()}
        self.views = views
        self.message.follow(views)
        self.table.setRowCount(len(views))
        for row, v in enumerate(views):
            state = (f"finished: {v.finish_reason}" if v.state is AppJobState.FINISHED
                     else v.state.value)
            cells = (v.name, v.device, state, None, format_hms(v.eta_s),
                     f"{v.iteration}" + (f" / {v.max_iter}" if v.max_iter else ""),
                     "–" if v.loss is None else f"{v.loss:.4g}")
            for col, text in enumerate(cells):
                if text is None:
                    continue
                item = self.table.item(row, col)
                if item is None:
                    item = QTableWidgetItem()
                    self.table.setItem(row, col, item)
                if item.text() != text:
                    item.setText(text)
                if col == 0:
                    item.setToolTip(str(v.folder))
            bar = self.table.cellWidget(row, 3)
            if not isinstance(bar, QProgressBar):
                bar = QProgressBar()
                bar.setRange(0, 1000)
                self.table.setCellWidget(row, 3, bar)
            bar.setValue(int(1000 * v.fraction))
            bar.setFormat(f"{100 * v.fraction:.0f}%")
        if keep:
            self._select_folders(keep)
        elif views and self.table.currentRow() < 0:
            self.table.selectRow(len(views) - 1)
            # the newest job, selected at start, was half hidden: in view once laid out
            QTimer.singleShot(0, self._show_selected)
        self._show_details()

    def selected(self) -> JobView | None:
        """The selected job (the first one when several are selected)."""
        views = self.selected_all()
        return views[0] if views else None

    def selected_all(self) -> list[JobView]:
        """Every selected job, in table order."""
        return [self.views[r] for r in self._selected_rows() if 0 <= r < len(self.views)]

    def _selected_rows(self) -> list[int]:
        """The selected rows, in table order."""
        model = self.table.selectionModel()
        return sorted({i.row() for i in model.selectedRows()}) if model is not None else []

    def showEvent(self, event: Any) -> None:
        """Shown (the app's start, a dock opened): the selected jobs in view."""
        super().showEvent(event)
        QTimer.singleShot(0, self._show_selected)

    def eventFilter(self, watched: Any, event: Any) -> bool:
        """The table's viewport resized (the window made shorter): the selection in view.

        The newest job, selected at start, was half hidden after the window shrank to the
        screen.
        """
        if (watched is self.table.viewport() and event.type() == QEvent.Type.Resize
                and self._selection_was_in_view(event.oldSize().height())):
            # only a selection that was in view is kept there: a table the user scrolled
            # elsewhere jumped back whenever the message line came or went
            QTimer.singleShot(0, self._show_selected)
        return super().eventFilter(watched, event)

    def _selection_was_in_view(self, height: int) -> bool:
        """Whether the last selected row lay wholly in a viewport ``height`` pixels tall.

        A viewport not yet laid out (height <= 0) counts as showing it.
        """
        rows = self._selected_rows()
        if not rows:
            return False
        if height <= 0:
            return True
        y = self.table.rowViewportPosition(rows[-1])
        return 0 <= y and y + self.table.rowHeight(rows[-1]) <= height

    def _show_selected(self) -> None:
        """Scroll the table to the selected rows (the last of them in view)."""
        rows = self._selected_rows()
        if rows:
            self.table.scrollTo(self.table.model().index(rows[-1], 0))
            self.table.scrollTo(self.table.model().index(rows[0], 0))

    def _select_folders(self, folders: set[Path]) -> None:
        model = self.table.selectionModel()
        flags = (QItemSelectionModel.SelectionFlag.Select
                 | QItemSelectionModel.SelectionFlag.Rows)
        current = {v.folder for v in self.selected_all()}
        if current == folders:
            return
        model.clearSelection()
        for row, v in enumerate(self.views):
            if v.folder in folders:
                model.select(self.table.model().index(row, 0), flags)

    def _selection_changed(self) -> None:
        self._shown_preview = None
        self._show_details()

    #: a loss file up to this size is read on the GUI thread (about 4000 rows, 20-30 ms), so a
    #: selected job shows its curve at once; a longer one on a worker
    LOSS_READ_INLINE_BYTES = 256 * 1024

    def _loss_of(self, folder: Path) -> tuple[Any, ...]:
        """The job's (iterations, loss, held-out, problem) as last read from its loss file.

        Read again only when the file changed; a long file on a worker, at most every 2 s and
        never more often than every 5 times its own read time (the curve then lags a poll).
        """
        import time

        from recon.udn.jobs import LOSS_FILE

        path = folder / RUN_DIR / LOSS_FILE
        try:
            st = path.stat()
            key = (st.st_size, st.st_mtime_ns)
        except OSError:  # none yet (or unreadable: the reader says why)
            return read_loss(folder)
        last = self._loss if self._loss is not None and self._loss[0] == folder else None
        if last is not None and last[1] == key:
            return last[2]
        if st.st_size <= self.LOSS_READ_INLINE_BYTES:
            got = read_loss(folder)
            self._loss = (folder, key, got)
            return got
        if not self._loss_reading and time.monotonic() >= self._loss_not_before:
            if self._loss_queue is None:
                self._loss_queue = TaskQueue("loss", self)
            self._loss_reading = True
            t0 = time.monotonic()

            def done(got: tuple[Any, ...]) -> None:
                self._loss_reading = False
                took = time.monotonic() - t0
                self._loss_not_before = time.monotonic() + max(2.0, 5.0 * took)
                v = self.selected()
                if v is not None and v.folder == folder:  # not another job's, chosen meanwhile
                    self._loss = (folder, key, got)
                    self._show_curves(*got[:3])

            def failed(exc: BaseException) -> None:
                self._loss_reading = False
                _log.warning("reading %s: %s", path, exc)

            self._loss_queue.submit(lambda: read_loss(folder), name="loss", on_done=done,
                                    on_error=failed)
        if last is not None:  # the last reading while the new one is made
            return last[2]
        empty = np.zeros(0)
        return empty, empty, empty, None

    def _show_curves(self, its: Any, loss: Any, held: Any) -> None:
        ok = np.isfinite(loss) & (loss > 0)
        self.loss_curve.setData(its[ok], np.log10(loss[ok]))
        okh = np.isfinite(held) & (held > 0)
        self.held_curve.setData(its[okh], np.log10(held[okh]))

    def _show_details(self) -> None:
        v = self.selected()
        self.cancel_button.setEnabled(v is not None and v.state.cancellable)
        self.resume_button.setEnabled(v is not None and v.can_resume)
        self.open_button.setEnabled(v is not None and bool(v.results))
        chosen = self.selected_all()
        self.combine_action.setEnabled(combine_refusal(chosen) is None)
        self.combine_fista_action.setEnabled(combine_refusal(chosen, with_fista=True) is None)
        self.combine_button.setEnabled(self.combine_action.isEnabled()
                                       or self.combine_fista_action.isEnabled())
        if v is None:
            self.details.setText("")
            self.details.setToolTip("")
            return
        mem = v.memory.get("peak_bytes", v.memory.get("total_bytes"))
        # one line of facts (the job's state and detail, which may be long, wrap on their own):
        # the table keeps the strip's height; the folder is the tooltip and 'Open folder'
        facts = [f"state: {v.state}"]
        if mem is not None:
            facts.append(f"memory (peak to expect) {_fmt_bytes(mem)}")
        if v.elapsed_s is not None:
            from recon.udn.jobs import format_hms

            facts.append(f"elapsed {format_hms(v.elapsed_s)}, ETA {format_hms(v.eta_s)}")
        lines = [" · ".join(facts)]
        if v.detail:
            lines.append(str(v.detail))
        its, loss, held, problem = self._loss_of(v.folder)
        if problem is not None:
            lines.append(f"loss curve not shown: {problem}")
        self.details.setText("\n".join(lines))
        self.details.setToolTip(str(v.folder))
        self._show_curves(its, loss, held)
        if v.last_preview is None or v.last_preview != self._shown_preview:
            img = None if v.last_preview is None else _load_png(v.last_preview)
            if img is not None:
                self.preview.set_image(img, (0.0, 255.0))
                self.preview.footer.setText(f"{v.name}: {v.last_preview.name}")
                self._shown_preview = v.last_preview
            else:  # none (yet), or not readable: not another job's (the last one shown stayed)
                self.preview.clear_image()
                self.preview.footer.setText(
                    f"{v.name}: no preview yet" if v.last_preview is None else
                    f"{v.name}: preview {v.last_preview.name} not readable")
                self._shown_preview = None

    # -- actions -------------------------------------------------------------------------------

    def new_job_dialog(self) -> NewJobDialog | None:
        """Ask for the settings of a job on the newest frame and the preview's PSF.

        One dialog at a time: while one is open it is brought to the front (two clicks opened
        two, and each could queue a job).
        """
        if self.dialog is not None and self.dialog.isVisible():
            self.dialog.raise_()
            self.dialog.activateWindow()
            return self.dialog
        m = self._current()
        frame = None if m is None else m.frame
        psf = None if m is None else m.psf
        if m is None or frame is None or psf is None:
            self.message.setText("a job needs a measurement (a live or snapped frame) and a PSF "
                                 "(the simulated bench's, a loaded one or a calibration)")
            return None
        problem = _size_problem(frame, psf)
        if problem is not None:  # said before the dialog is filled in, not after
            self.message.setText(problem)
            return None
        src = (f"measurement: frame {frame.frame_id} ({frame.shape[0]}x{frame.shape[1]}, "
               f"{frame.backend}); PSF: {m.psf_source or 'current'}")
        hashes = None
        try:
            from recon.suggest import input_hashes

            hashes = input_hashes(frame.pixels, psf)
        except Exception:  # an odd frame: no suggestions, the dialog still works
            hashes = None
        dlg = NewJobDialog(frame.shape, src, self, hashes=hashes,
                           suggestion_dirs=self.suggestion_dirs,
                           run_planner=lambda cancelled: _plan_measurement(m, cancelled),
                           save_dir=self.suggestion_dirs[0])
        if self.last_job:  # the settings of the last job queued, not the defaults again
            dlg.restore(self.last_job)
        self.dialog = dlg
        dlg.accepted.connect(lambda: self._create_from_dialog(dlg, m))
        dlg.show()
        return dlg

    def _create_from_dialog(self, dlg: NewJobDialog, m: Measurement) -> None:
        self.last_job = dlg.remembered()
        self.create_job(m, dlg.name.text() or "udn", int(dlg.downsample.value()),
                        dlg.sections(), seeds=int(dlg.seeds.value()))

    def create_job(self, m: Measurement, name: str, downsample: int,
                   sections: dict[str, dict[str, Any]], seeds: int = 1) -> Path | None:
        """Write and queue a job for ``m``'s frame and PSF; returns its (first) folder.

        ``seeds`` > 1 queues that many jobs with ``optimizer.seed`` 0, 1, ... (named
        ``NAME-sN``), for :meth:`combine_selected`; they run one after another.
        """
        frame, psf = m.frame, m.psf
        try:  # what the dialog checks: a job it would refuse is not queued from here either
            estimate_job_memory(frame.shape, int(downsample), sections)
        except Exception as exc:
            self.message.setText(f"cannot queue the job: {exc}")
            return None
        problem = _size_problem(frame, psf)
        if problem is not None:
            self.message.setText(problem)
            return None
        dark = _dark_level(m)
        meta = {"frame": frame.metadata(), "psf_source": m.psf_source,
                "psf_path": m.psf_path or None, "dark": dark}
        folders: list[Path] = []
        error = ""
        for seed in range(max(1, int(seeds))):
            secs = {k: dict(v) for k, v in sections.items()}
            if seeds > 1:
                secs.setdefault("optimizer", {})["seed"] = seed
            try:
                folders.append(create_job(self.queue.jobs_dir,
                                          f"{name}-s{seed}" if seeds > 1 else name,
                                          frame.pixels, psf, downsample=downsample, dark=dark,
                                          sections=secs, measurement_metadata=meta))
            except Exception as exc:
                error = f"cannot create the job{f' for seed {seed}' if seeds > 1 else ''}: {exc}"
                break
        if not folders:
            self.message.setText(error)
            return None
        text = (f"queued {folders[0].name}" if len(folders) == 1 else
                f"queued {len(folders)} jobs (seeds 0-{len(folders) - 1}): combine them when "
                "they have finished")
        self.message.setText(text + (f"; {error}" if error else ""), about=folders[-1])
        self.refresh()
        self._select_folders(set(folders))
        self._show_selected()  # new jobs are listed last: bring them into view
        for folder in folders:
            self.job_created.emit(folder)
        return folders[0]

    def combine_selected(self, with_fista: bool = False) -> Any:
        """Average the selected finished jobs (``with_fista``: their means, and FISTA-TV).

        Runs on a worker thread; the message says so, then where the result is (or why it
        could not be made). Returns the queued task, or None when refused at once (too few
        finished jobs, or a combine already running).
        """
        views = self.selected_all()
        what = f"{len(views)} job{'s' if len(views) != 1 else ''}" + (
            " (FISTA-TV)" if with_fista else "")
        if self._combining is not None:
            self.message.setText(f"cannot combine {what} now: combining {self._combining} "
                                 "is still running; try again when it has finished")
            return None
        refusal = combine_refusal(views, with_fista)
        if refusal is not None:
            self.message.setText(f"cannot combine: {refusal}")
            return None
        if self._combine_queue is None:
            self._combine_queue = TaskQueue("combine", self)
        jobs_dir = self.queue.jobs_dir
        self._combining = what
        self.message.setText(f"combining {what}"
                             + (": the automatic tau takes seconds to a minute" if with_fista
                                else "") + "…")
        return self._combine_queue.submit(
            lambda: combine_jobs(views, jobs_dir, with_fista=with_fista), name="combine",
            on_done=lambda res: self._combined(res, len(views)),
            on_error=self._combine_failed)

    def _combined(self, res: Any, n: int) -> None:
        if self._combine_queue is None:  # stopped meanwhile: the window is closing
            return
        self._combining = None
        text = f"ensemble of {n} job{'s' if n != 1 else ''} ({res.estimate} estimates)"
        if res.fista is not None:
            text += f" and FISTA-TV (tau {res.fista['tau']:.3g})"
        text += f" written to {res.paths[0]}"
        psnr = (res.scores or {}).get("psnr")
        if psnr is not None:
            text += f" (PSNR {psnr:.2f} dB against the truth)"
        if res.note is not None:
            text += f"; {res.note}"
        self.message.setText(text)

    def _combine_failed(self, exc: BaseException) -> None:
        if self._combine_queue is None:
            return
        self._combining = None
        self.message.setText(f"cannot combine: {exc}")

    def cancel_selected(self) -> None:
        """Cancel the selected job (withdraw it, or stop its run at the next iteration)."""
        v = self.selected()
        if v is None:
            return
        try:
            self.message.setText(cancel_job(v.folder), about=v.folder)
        except Exception as exc:
            self.message.setText(f"cannot cancel: {exc}", about=v.folder)
        self.refresh()

    def resume_selected(self) -> None:
        """Queue a resume of the selected (interrupted or cancelled) run."""
        v = self.selected()
        if v is None:
            return
        more, longer = v.resume_max_iter, v.resume_time_limit_s
        again = not (v.folder / RUN_DIR / "run.json").is_file()  # withdrawn before it ran
        try:
            queue_resume(v.folder, max_iter=more)
        except Exception as exc:
            self.message.setText(f"cannot resume: {exc}")
            return
        if again:
            said = f"{v.name} queued again (it was withdrawn before it ran)"
        else:
            said = f"resume of {v.name} queued" + (
                f" (to {more} iterations)" if more else
                f" (with a time limit of {longer / 3600:.3g} h)" if longer else "")
        self.message.setText(said, about=v.folder)
        self.refresh()

    def open_selected(self) -> ResultDialog | None:
        """Show the selected job's best and final estimates."""
        v = self.selected()
        if v is None or not v.results:
            return None
        try:
            dlg = ResultDialog(v, self)
        except Exception as exc:
            self.message.setText(f"cannot open the result: {exc}")
            return None
        self.result_dialog = dlg
        dlg.show()
        return dlg

    def open_folder(self) -> None:
        """Open the selected job's folder (or the jobs folder) in the file manager."""
        v = self.selected()
        target = v.folder if v is not None else self.queue.jobs_dir
        QDesktopServices.openUrl(QUrl.fromLocalFile(str(target)))


def _dark_level(m: Measurement) -> float:
    """The measurement's dark level: the preview's rule (:func:`frame_dark_level`)."""
    from app.gui.preview_engine import frame_dark_level

    return frame_dark_level(m.frame.pixels, m.dark, getattr(m.frame, "black_level", None))


def _plan_measurement(m: Measurement, cancelled: Callable[[], bool] | None = None) -> Any:
    """The plan ``lenslesscam plan`` makes of the dark-corrected frame and the PSF (no budget).

    ``recon.plan.make_plan``, then, for FISTA-TV, tau and iterations chosen from held-out
    pixels (:func:`recon.plan.auto_tau_plan`) as the command does when no tau is given: the
    app's plan kept the fixed default tau (1e-3 where the command chose 1e-4).
    """
    from recon.plan import auto_tau_plan, make_plan

    psf = np.asarray(m.psf, dtype=np.float32)
    meas = np.clip(np.asarray(m.frame.pixels, dtype=np.float32) - _dark_level(m), 0, None)
    plan = make_plan(psf, meas)
    return (auto_tau_plan(plan, psf, meas, cancel=cancelled) if plan.method == "fista-tv"
            else plan)


def _size_problem(frame: Any, psf: Any) -> str | None:
    """Why a UDN job cannot take this frame and PSF (sizes HxW, as everywhere), or None."""
    if tuple(frame.shape) == tuple(psf.shape):
        return None
    return (f"the frame ({frame.shape[0]}x{frame.shape[1]}) and the PSF "
            f"({psf.shape[-2]}x{psf.shape[-1]}) differ in size (HxW): a UDN job needs a "
            "full-sensor frame and a PSF calibrated for that sensor (a camera ROI makes the "
            "frame smaller: Full sensor)")


class _MessageLabel(ElidedLabel):
    """The panel's last message, with the time it was said; no space while empty.

    One line, cut with '…' and whole in the tooltip (a combine's 776-character message took
    four lines and left the table two rows). A click dismisses it. A message about one job
    (``about``: its folder) goes when that job's state changes ("queued …" once it runs,
    "cancel requested …" once it stopped); the others stay until the next one.
    """

    def __init__(self) -> None:
        super().__init__("")
        self.setVisible(False)
        self.about: Path | None = None
        self.about_state: Any = None  # the job's state at the first poll after the message

    def setText(self, text: str, about: Path | None = None) -> None:
        """Show ``text`` (hidden when empty), stamped with the time."""
        import time

        self.about, self.about_state = (about if text else None), None
        super().setText(f"{time.strftime('%H:%M:%S')}  {text}" if text else "")
        self.setVisible(bool(text))

    def follow(self, views: list[JobView]) -> None:
        """Clear a message about a job whose state has changed since (see the class)."""
        if self.about is None:
            return
        state = next((v.state for v in views if v.folder == self.about), None)
        if self.about_state is None:
            self.about_state = state
        elif state != self.about_state:
            self.setText("")

    def mousePressEvent(self, event: Any) -> None:
        """A click dismisses the message."""
        self.setText("")
        super().mousePressEvent(event)


def _load_png(path: Path) -> Any:
    try:
        from PIL import Image

        with Image.open(path) as im:
            return np.asarray(im.convert("L"), dtype=np.float32)
    except (OSError, ValueError):
        return None
