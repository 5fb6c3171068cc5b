"""Small widgets used everywhere in the app.

Spin boxes and combo boxes that take the mouse wheel only when they have the keyboard focus:
scrolling a panel with the wheel passes over them without changing a camera setting (a wheel
over an unfocused frame-rate box once changed 20 Hz to 5 Hz). They take the focus by click or
Tab (``Qt.StrongFocus``), not by the wheel. Every spin box and combo box of the app is one of
these (``tests/gui`` checks it).

:func:`never_wider` makes a label (a footer, a status line, a banner) unable to widen the window.
"""

from __future__ import annotations

import math
import re
from typing import Any

from PySide6.QtCore import Qt
from PySide6.QtGui import QValidator, QWheelEvent
from PySide6.QtWidgets import (
    QAbstractSpinBox,
    QComboBox,
    QDoubleSpinBox,
    QLabel,
    QSizePolicy,
    QSpinBox,
    QWidget,
)

from recon.formats import INT_LIMIT

__all__ = ["ComboBox", "DoubleSpinBox", "ElidedLabel", "SpinBox", "WheelOnFocus", "double_spin",
           "never_wider"]


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


def _core(box: QAbstractSpinBox, text: str) -> str:
    """A spin box's ``text`` without its prefix and suffix, stripped."""
    b: Any = box
    core = text
    if b.suffix() and core.endswith(b.suffix()):
        core = core[:-len(b.suffix())]
    if b.prefix() and core.startswith(b.prefix()):
        core = core[len(b.prefix()):]
    return core.strip()


def _number(box: QAbstractSpinBox, text: str, kind: type) -> Any:
    """The finite number a spin box's ``text`` holds (prefix and suffix off), else None."""
    try:
        value = kind(_core(box, text))
    except ValueError:
        return None
    return value if math.isfinite(value) else None


_PARTIAL_NUMBER = re.compile(r"[+-]?\d*\.?\d*(?:[eE][+-]?\d*)?")


def _partial_number(box: QAbstractSpinBox, text: str) -> bool:
    """Whether ``text`` (prefix and suffix off) is the beginning of a number: '1e', '2e-'."""
    return _PARTIAL_NUMBER.fullmatch(_core(box, text)) is not None


def _any_notation(box: QAbstractSpinBox, qt_result: Any, text: str, pos: int) -> Any:
    """Qt's validation of ``text``, with numbers in any notation let through.

    A number in any notation, or the beginning of one ('1e', '2e-'), is Intermediate (Qt
    refused the keystroke): corrected to the box's range and step when the edit ends.
    """
    state = qt_result[0] if isinstance(qt_result, tuple) else qt_result
    if state != QValidator.State.Invalid:
        return qt_result
    if _number(box, text, float) is None and not _partial_number(box, text):
        return qt_result
    return (QValidator.State.Intermediate, text, pos)


def _whole(box: QAbstractSpinBox, text: str) -> int | None:
    """The whole number nearest to the number ``text`` holds in any notation, else None.

    Beyond :data:`INT_LIMIT` it is that limit (with the sign), which the box then corrects to
    its bound: 1e30 typed into Iterations became the box's minimum, 1 (None made Qt fall back
    to its own parse), where 99999999999 became its maximum.
    """
    value = _number(box, text, float)
    if value is None:
        return None
    return math.floor(max(-INT_LIMIT, min(INT_LIMIT, value)) + 0.5)


def _nearest_text(box: QAbstractSpinBox, text: str, kind: type) -> str:
    """``text`` of a spin box as the nearest value in its range, prefix and suffix kept.

    Unchanged when it holds no number.
    """
    b: Any = box
    value = _number(box, text, kind)
    if value is None:
        return text
    value = min(max(value, b.minimum()), b.maximum())
    return f"{b.prefix()}{b.textFromValue(value)}{b.suffix()}"


class SpinBox(WheelOnFocus, QSpinBox):
    """A :class:`QSpinBox` that takes the wheel only when focused.

    A typed value out of range becomes the nearest bound, not the previous value (Qt's
    default: 0.9 typed into a 0-0.5 box kept 0, the value of the "0" typed on the way).
    """

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self._wheel_guard_init()
        self.setCorrectionMode(QAbstractSpinBox.CorrectionMode.CorrectToNearestValue)

    def validate(self, text: str, pos: int) -> object:
        """Qt's validation, except that any number may be typed, in any notation.

        '1e4' lost its 'e' and became 14 (and '2.5' 25); now it is 10000 (2.5: the nearest
        whole number), corrected to the range when the edit ends.
        """
        return _any_notation(self, super().validate(text, pos), text, pos)

    def valueFromText(self, text: str) -> int:
        """The typed number in any notation, the nearest whole number."""
        value = _whole(self, text)
        return value if value is not None else int(super().valueFromText(text))

    def fixup(self, text: str) -> str:
        """The nearest whole number in the range (2.5 is 3; 1e9 in a 1-100 box is 100)."""
        value = _whole(self, text)
        if value is None:
            return text
        value = min(max(value, self.minimum()), self.maximum())
        return f"{self.prefix()}{self.textFromValue(value)}{self.suffix()}"


class DoubleSpinBox(WheelOnFocus, QDoubleSpinBox):
    """A :class:`QDoubleSpinBox` that takes the wheel only when focused.

    A typed value out of range becomes the nearest bound (as :class:`SpinBox`).
    """

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self._wheel_guard_init()
        self.setCorrectionMode(QAbstractSpinBox.CorrectionMode.CorrectToNearestValue)

    def validate(self, text: str, pos: int) -> object:
        """Qt's validation, except that any finite number may be typed, in any notation.

        One above the maximum (or with more decimals than shown) is corrected to the nearest
        valid value when the edit ends; Qt refused the keystroke, so 0.9 typed into a 0-0.5
        box stopped at "0." and became 0, and 1e-5 lost its "e" and "-" and became 15.
        """
        return _any_notation(self, super().validate(text, pos), text, pos)

    def valueFromText(self, text: str) -> float:
        """The typed number in any notation (2e-4 as well as 0.0002), to the box's decimals.

        4e-4 in a 3-decimal box is 0, as 0.0004 typed is: the value is what is shown.
        """
        value = _number(self, text, float)
        if value is None:
            return float(super().valueFromText(text))
        return round(float(value), self.decimals())

    def fixup(self, text: str) -> str:
        """A number out of range becomes the nearest bound (shown with the box's decimals)."""
        return _nearest_text(self, text, float)


class SciSpinBox(DoubleSpinBox):
    """A spin box for a value that spans decades (a TV weight, a learning rate).

    Shown with up to 6 significant digits (so what is shown is the value: with 3, Return on
    0.000123456 made it 0.000123), typed in any notation, kept to 1e-9.

    A fixed number of decimals showed 3e-6 as 0.00000 and gave back 0.
    """

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setDecimals(9)

    def textFromValue(self, value: float) -> str:
        """Up to 6 significant digits: 0.0003, 2.5e-06, 0.000123456."""
        return f"{value:.6g}"

    def validate(self, text: str, pos: int) -> Any:
        """Numbers in any notation; their beginnings while typing."""
        v = _number(self, text, float)
        if v is None:
            ok = _partial_number(self, text)
            return (QValidator.State.Intermediate if ok else QValidator.State.Invalid, text, pos)
        inside = self.minimum() <= v <= self.maximum()
        return (QValidator.State.Acceptable if inside else QValidator.State.Intermediate,
                text, pos)


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


class ElidedLabel(QLabel):
    """A one-line label: text wider than the label ends in '…', the whole of it in the tooltip.

    For status lines above other controls (a status that wrapped moved the buttons below it
    when it changed); :meth:`text` is the whole text.
    """

    def __init__(self, text: str = "", parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self._full = ""
        never_wider(self)
        self.setText(text)

    def text(self) -> str:
        """The whole text (what is shown may be cut)."""
        return self._full

    def setText(self, text: str) -> None:
        """Show ``text``, cut to the label's width."""
        self._full = text
        self.setToolTip(text)
        self._elide()

    def resizeEvent(self, event: Any) -> None:
        """Cut the text again to the new width."""
        super().resizeEvent(event)
        self._elide()

    def _elide(self) -> None:
        width = self.width() if self.width() > 0 else 10**6
        one_line = " ".join(self._full.split())  # an exception's text may hold newlines
        shown = self.fontMetrics().elidedText(one_line, Qt.TextElideMode.ElideRight, width)
        if shown != super().text():
            super().setText(shown)
