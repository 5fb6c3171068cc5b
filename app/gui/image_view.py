"""An image panel: pyqtgraph image (row-major) with histogram/LUT, fixed levels, overlays, ROI.

Levels stay fixed between frames (no auto-levels per frame: it costs time and makes the live
view flicker); :meth:`ImagePanel.autoscale` sets them from the current image on demand, and the
first image of a new shape is autoscaled once; the *auto levels* option rescales every image
(continuous auto-levels, for a live frame whose brightness changes). Pixels at or above
``saturation_level`` are painted red by a second image item on top. An optional rectangular ROI
reports its statistics. The pixel under the mouse (position and value) is shown in the header;
a right click opens the image menu (autoscale, export the view as PNG, save the data as TIFF).
The footer and header lines never widen the window: long text is cut, not laid out wider.
"""

from __future__ import annotations

import gc
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pyqtgraph as pg
from PySide6.QtCore import QPoint, QPointF, Qt, Signal
from PySide6.QtWidgets import (
    QCheckBox,
    QFileDialog,
    QHBoxLayout,
    QLabel,
    QMenu,
    QPushButton,
    QVBoxLayout,
    QWidget,
)

from app.gui.widgets import never_wider

__all__ = ["ImagePanel", "configure_pyqtgraph"]

_configured = False
_collector: Any = None  # the GUI-thread garbage collector (configure_pyqtgraph)


def configure_pyqtgraph() -> None:
    """Global GUI settings, once per process (call with the QApplication running).

    Row-major images (``image[row, col]``) for pyqtgraph, and Python's cyclic garbage
    collection moved to the GUI thread: automatic collection off, a 1 s timer collects
    (pyqtgraph's ``GarbageCollector``). Otherwise a worker thread (the preview's tau search,
    a driver's stream) can run the collector, destroy a Qt object caught in a reference
    cycle and deadlock with the GUI thread: it waits for the GIL holding a Qt lock that the
    GUI thread, holding the GIL, waits for (seen in the GUI tests as a hang in a paint event).
    """
    global _configured, _collector
    if not _configured:
        pg.setConfigOptions(imageAxisOrder="row-major", antialias=False)
        from pyqtgraph.util.garbage_collector import GarbageCollector

        _collector = GarbageCollector(interval=1.0)
        _configured = True
    gc.disable()  # (again: a test harness may have turned it back on between windows)


class ImagePanel(QWidget):
    """Title, image with histogram/LUT, a footer line for readouts.

    Signals: ``roi_changed(x, y, w, h)`` in image pixels when the user moves the ROI.
    """

    roi_changed = Signal(int, int, int, int)

    def __init__(
        self,
        title: str,
        *,
        with_roi: bool = False,
        with_saturation: bool = False,
        auto_levels_option: bool = False,
        parent: QWidget | None = None,
    ) -> None:
        super().__init__(parent)
        configure_pyqtgraph()
        self.setObjectName(f"panel-{title.lower().replace(' ', '-')}")
        self._shape: tuple[int, ...] | None = None
        self._image: npt.NDArray[np.generic] | None = None
        self.saturation_level: float | None = None
        self.saturated = 0

        self.title = QLabel(f"<b>{title}</b>")
        # the title may be cut where the window is narrow: its full width in every panel made
        # the main window 1042 px wide at least, wider than a 1024 px screen
        self.title.setMinimumWidth(24)
        self.title.setToolTip(title)
        self.autoscale_button = QPushButton("Autoscale")
        self.autoscale_button.setToolTip("Set the display levels from the current image")
        self.autoscale_button.clicked.connect(self.autoscale)
        self.auto_levels = QCheckBox("auto levels")
        self.auto_levels.setToolTip("Rescale the levels at every image")
        self.auto_levels.setVisible(auto_levels_option)
        self.cursor_label = QLabel("")
        self.cursor_label.setObjectName("cursor")
        never_wider(self.cursor_label)
        head = QHBoxLayout()
        head.addWidget(self.title)
        head.addWidget(self.cursor_label, 1)
        head.addWidget(self.auto_levels)
        head.addWidget(self.autoscale_button)

        self.graphics = pg.GraphicsLayoutWidget()
        self.graphics.setMinimumSize(120, 100)
        self.graphics.setContextMenuPolicy(Qt.ContextMenuPolicy.CustomContextMenu)
        self.graphics.customContextMenuRequested.connect(self._context_menu)
        self.view = self.graphics.addViewBox(lockAspect=True, invertY=True, enableMenu=False)
        self.item = pg.ImageItem()
        self.view.addItem(self.item)
        self.overlay = pg.ImageItem()
        self.overlay.setZValue(10)
        self.overlay.setVisible(False)
        self.view.addItem(self.overlay)
        self.hist = pg.HistogramLUTItem(image=self.item)
        self.graphics.addItem(self.hist)
        self._with_saturation = with_saturation

        self.roi: pg.RectROI | None = None
        if with_roi:
            self.roi = pg.RectROI([10, 10], [40, 40], pen=pg.mkPen("y", width=1))
            self.roi.addScaleHandle([0, 0], [1, 1])
            self.roi.setZValue(20)
            self.roi.setVisible(False)
            self.view.addItem(self.roi)
            self.roi.sigRegionChangeFinished.connect(self._emit_roi)

        self.footer = QLabel("–")
        self.footer.setObjectName("footer")
        self.footer.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.footer.setWordWrap(True)  # readouts wrap at " · " instead of being cut
        never_wider(self.footer)
        self._message_until = 0.0  # a save's message outlives the frames that follow it
        self.message = QLabel("")
        self.message.setWordWrap(True)
        never_wider(self.message)
        self.message.setStyleSheet("color: #b00;")
        self.message.setVisible(False)

        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        lay.addLayout(head)
        lay.addWidget(self.graphics, 1)
        lay.addWidget(self.message)
        lay.addWidget(self.footer)
        self.graphics.scene().sigMouseMoved.connect(self._mouse_moved)
        self.cursor: tuple[int, int, float] | None = None

    # -- images --------------------------------------------------------------------------------

    @property
    def image(self) -> npt.NDArray[np.generic] | None:
        """The image shown last."""
        return self._image

    @property
    def levels(self) -> tuple[float, float]:
        """Current display levels."""
        lo, hi = self.hist.getLevels()
        return float(lo), float(hi)

    def set_levels(self, lo: float, hi: float) -> None:
        """Fix the display levels."""
        if not hi > lo:
            hi = lo + 1.0
        self.hist.setLevels(float(lo), float(hi))

    def set_image(
        self, image: npt.NDArray[np.generic], levels: tuple[float, float] | None = None
    ) -> None:
        """Show ``image`` (H, W); ``levels`` fixes the levels (else they stay as they are)."""
        first = self._shape != image.shape
        self._image = image
        self.item.setImage(image, autoLevels=False)
        if levels is not None and (self.auto_levels.isChecked() or first
                                    or not self.auto_levels.isVisible()):
            self.set_levels(*levels)
        elif first or self.auto_levels.isChecked():
            self.autoscale()
        if first:
            self._shape = image.shape
            self.view.autoRange(padding=0.0)
            if self.roi is not None:
                h, w = image.shape[:2]
                self.roi.setPos([w // 4, h // 4])
                self.roi.setSize([w // 2, h // 2])
        if self._with_saturation:
            self._update_saturation(image)
        if time.monotonic() >= self._message_until:
            self.set_message("")

    def clear_image(self) -> None:
        """Show no image (the next :meth:`set_image` is taken as a first one)."""
        self._image = None
        self._shape = None
        self.item.clear()
        self.overlay.setVisible(False)
        self.saturated = 0

    def _update_saturation(self, image: npt.NDArray[np.generic]) -> None:
        level = self.saturation_level
        if level is None:
            self.saturated = 0
            self.overlay.setVisible(False)
            return
        mask = image >= level
        self.saturated = int(np.count_nonzero(mask))
        if self.saturated == 0:
            self.overlay.setVisible(False)
            return
        rgba = np.zeros((*image.shape[:2], 4), dtype=np.uint8)
        rgba[mask] = (255, 0, 0, 255)
        self.overlay.setImage(rgba, autoLevels=False, levels=(0, 255))
        self.overlay.setVisible(True)

    def autoscale(self) -> None:
        """Levels from the current image: its minimum and maximum."""
        if self._image is None or self._image.size == 0:
            return
        lo = float(np.min(self._image))
        hi = float(np.max(self._image))
        self.set_levels(lo, hi)

    def set_message(self, text: str, hold_s: float = 0.0) -> None:
        """Show (or clear) a message under the image (errors).

        ``hold_s``: new images do not clear it for that long (a save's outcome: the next
        frame, 50 ms later, cleared it before anyone could read it).
        """
        self._message_until = time.monotonic() + hold_s if hold_s > 0 else 0.0
        if text == self.message.text() and bool(text) == self.message.isVisible():
            return
        self.message.setText(text)
        self.message.setVisible(bool(text))

    # -- cursor and context menu --------------------------------------------------------------

    def pixel_at(self, scene_pos: QPointF) -> tuple[int, int, float] | None:
        """(x, y, value) of the image pixel at a scene position, None outside the image."""
        img = self._image
        if img is None:
            return None
        p = self.view.mapSceneToView(scene_pos)
        x, y = int(np.floor(p.x())), int(np.floor(p.y()))
        if not (0 <= y < img.shape[0] and 0 <= x < img.shape[1]):
            return None
        return x, y, float(np.asarray(img[y, x]).mean())

    def _mouse_moved(self, scene_pos: QPointF) -> None:
        self.cursor = self.pixel_at(scene_pos)
        if self.cursor is None:
            self.cursor_label.setText("")
            return
        x, y, v = self.cursor
        self.cursor_label.setText(f"x {x}  y {y}  value {v:.6g}")

    def _context_menu(self, pos: QPoint) -> None:
        self.context_menu().exec(self.graphics.mapToGlobal(pos))

    def context_menu(self) -> QMenu:
        """The image menu: autoscale, reset the zoom, export the view, save the data."""
        menu = QMenu(self)
        menu.addAction("Autoscale levels", self.autoscale)
        menu.addAction("Reset zoom", lambda: self.view.autoRange(padding=0.0))
        menu.addSeparator()
        menu.addAction("Export view as PNG…", self._ask_export_view)
        act = menu.addAction("Save image data as TIFF…", self._ask_save_data)
        act.setEnabled(self._image is not None)
        return menu

    def export_view(self, path: str | Path) -> Path:
        """Save what the panel shows (image, levels, overlays) as a PNG."""
        from recon.atomic import atomic_write

        def write(tmp: Path) -> None:
            if not self.graphics.grab().save(str(tmp), "PNG"):
                raise OSError(f"cannot write {path}")

        return atomic_write(path, write)

    def save_data(self, path: str | Path) -> Path:
        """Save the image's values (float32 or the camera's codes) as a TIFF, atomically."""
        if self._image is None:
            raise ValueError("no image to save")
        import tifffile

        from recon.atomic import atomic_write
        from recon.formats import provenance

        data = np.ascontiguousarray(self._image)
        meta = json.dumps({"format": "lenslesscam-view", "format_version": 1,
                           "panel": self.objectName(), "levels": list(self.levels),
                           "provenance": provenance()}, default=str)

        def write(tmp: Path) -> None:
            tifffile.imwrite(tmp, data, photometric="minisblack", description=meta,
                             metadata=None)

        return atomic_write(path, write)

    def _ask_export_view(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Export view", "view.png", "PNG (*.png)")
        if path:
            self._save_said(self.export_view, path, ".png")

    def _ask_save_data(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Save image data", "image.tif",
                                              "TIFF (*.tif)")
        if path:
            self._save_said(self.save_data, path, ".tif")

    def _save_said(self, save: Any, path: str, suffix: str) -> None:
        """``save(path)``, the dialog's suffix added to a bare name; the outcome is said.

        Under the image, held there a while (success was not said, a failure vanished at once).
        """
        target = Path(path)
        if not target.suffix:
            target = target.with_suffix(suffix)
        try:
            written = save(target)
        except (OSError, ValueError) as exc:
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            self.set_message(f"not saved: {target}: {why}", hold_s=15.0)
            return
        self.set_message(f"saved {written or target}", hold_s=8.0)

    # -- ROI -----------------------------------------------------------------------------------

    def set_roi_visible(self, visible: bool) -> None:
        """Show or hide the ROI rectangle."""
        if self.roi is not None:
            self.roi.setVisible(visible)

    def roi_rect(self) -> tuple[int, int, int, int] | None:
        """(x, y, w, h) of the ROI clipped to the image, or None when hidden or empty."""
        if self.roi is None or not self.roi.isVisible() or self._image is None:
            return None
        x, y = (round(float(v)) for v in self.roi.pos())
        w, h = (round(float(v)) for v in self.roi.size())
        ih, iw = self._image.shape[:2]
        x0, y0 = max(0, x), max(0, y)
        x1, y1 = min(iw, x + w), min(ih, y + h)
        if x1 <= x0 or y1 <= y0:
            return None
        return x0, y0, x1 - x0, y1 - y0

    def roi_stats(self) -> tuple[float, float] | None:
        """(mean, max) inside the ROI."""
        r = self.roi_rect()
        if r is None or self._image is None:
            return None
        x, y, w, h = r
        patch = self._image[y : y + h, x : x + w]
        return float(patch.mean()), float(patch.max())

    def _emit_roi(self) -> None:
        r = self.roi_rect()
        if r is not None:
            self.roi_changed.emit(*r)

