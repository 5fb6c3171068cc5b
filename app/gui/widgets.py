"""Small widgets used everywhere in the app.

Spin boxes and combo boxes that take the mouse wheel only when they have the keyboard focus:
scrolling a panel with the wheel passes over them without changing a camera setting (a wheel
over an unfocused frame-rate box once changed 20 Hz to 5 Hz). They take the focus by click or
Tab (``Qt.StrongFocus``), not by the wheel. Every spin box and combo box of the app is one of
these (``tests/gui`` checks it).

:func:`never_wider` makes a label (a footer, a status line, a banner) unable to widen the window.
"""

from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtGui import QWheelEvent
from PySide6.QtWidgets import QComboBox, QDoubleSpinBox, QLabel, QSizePolicy, QSpinBox, QWidget

__all__ = ["ComboBox", "DoubleSpinBox", "SpinBox", "WheelOnFocus", "double_spin", "never_wider"]


class WheelOnFocus:
    """Mixin: the wheel changes the value only while the widget has the focus.

    Without the focus the wheel event is ignored, so it goes to the parent (the scroll area
    scrolls).
    """

    def _wheel_guard_init(self) -> None:
        self.setFocusPolicy(Qt.FocusPolicy.StrongFocus)  # type: ignore[attr-defined]

    def wheelEvent(self, event: QWheelEvent) -> None:
        """Pass the wheel to the parent unless focused."""
        if not self.hasFocus():  # type: ignore[attr-defined]
            event.ignore()
            return
        super().wheelEvent(event)  # type: ignore[misc]


class SpinBox(WheelOnFocus, QSpinBox):
    """A :class:`QSpinBox` that takes the wheel only when focused."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self._wheel_guard_init()


class DoubleSpinBox(WheelOnFocus, QDoubleSpinBox):
    """A :class:`QDoubleSpinBox` that takes the wheel only when focused."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self._wheel_guard_init()


class ComboBox(WheelOnFocus, QComboBox):
    """A :class:`QComboBox` that takes the wheel only when focused."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self._wheel_guard_init()


def double_spin(
    lo: float, hi: float, decimals: int, step: float, suffix: str = ""
) -> DoubleSpinBox:
    """A :class:`DoubleSpinBox` with range, decimals, step and suffix; no keyboard tracking."""
    s = DoubleSpinBox()
    s.setRange(lo, hi)
    s.setDecimals(decimals)
    s.setSingleStep(step)
    s.setSuffix(suffix)
    s.setKeyboardTracking(False)
    return s


def never_wider(label: QLabel) -> QLabel:
    """Make ``label``'s text never widen its layout (long text wraps or is cut at the edge)."""
    label.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Preferred)
    label.setMinimumWidth(0)
    return label
