"""``plan --out`` and ``trade`` record which measurement they were made for, and the app's
job dialog logic (:func:`recon.suggest.find_suggestions`) offers them for that frame first,
then for other frames of the same PSF."""

from __future__ import annotations

import json

import numpy as np
import tifffile

from app.cli import main
from recon.models import build_model
from recon.readers import load_psf_any
from recon.simulate import simulate, synthetic_psf
from recon.suggest import find_suggestions, input_hashes


def _snapshot(tmp_path, seed: int = 0):
    """A raw uint16 frame as the app snaps it, saved as TIFF, and a PSF image file."""
    psf = synthetic_psf((48, 64), n_points=20, seed=1)
    rng = np.random.default_rng(seed)
    scene = np.zeros((1, 1, 48, 64), dtype=np.float32)
    scene[0, 0, 12:36, 16:48] = rng.random((24, 32), dtype=np.float32)
    sim = simulate(build_model("2d", psf), scene, noise=0.01, seed=seed)
    frame = (100 + 3000 * np.clip(sim.meas[0], 0, None) / sim.meas.max()).astype(np.uint16)
    tifffile.imwrite(tmp_path / f"snap{seed}.tif", frame)
    tifffile.imwrite(tmp_path / "psf.tif", (60000 * psf / psf.max()).astype(np.uint16))
    return frame


def test_plan_out_is_offered_for_its_frame_and_not_for_another(tmp_path, capsys):
    frame = _snapshot(tmp_path, 0)
    other = _snapshot(tmp_path, 1)
    sugg = tmp_path / "suggestions"
    sugg.mkdir()
    assert main(["plan", "--meas", str(tmp_path / "snap0.tif"), "--psf",
                 str(tmp_path / "psf.tif"), "--no-probe", "--tau", "1e-3",
                 "--out", str(sugg / "plan.json")]) == 0
    saved = json.loads((sugg / "plan.json").read_text())
    assert set(saved["inputs"]) == {"measurement", "psf"}
    # the app hashes the snapped frame's pixels and the PSF as it loads it
    app_psf = load_psf_any(tmp_path / "psf.tif")
    found = find_suggestions([sugg], input_hashes(frame, app_psf))
    assert [s.path.name for s in found] == ["plan.json"] and found[0].source == "plan"
    assert found[0].same_measurement
    # another frame with the same PSF (a live camera's next frame): offered, marked so (a
    # live camera's plans were never offered again); another PSF: not offered
    (again,) = find_suggestions([sugg], input_hashes(other, app_psf))
    assert not again.same_measurement and "another frame, same PSF" in again.label
    assert again.detail.startswith("made on another measurement with this PSF")
    assert find_suggestions([sugg], input_hashes(other, app_psf[::-1].copy())) == []


def test_trade_records_its_inputs_beside_the_csv(tmp_path, capsys):
    _snapshot(tmp_path, 0)
    out = tmp_path / "trade"
    assert main(["trade", "--meas", str(tmp_path / "snap0.tif"), "--psf",
                 str(tmp_path / "psf.tif"), "--quick", "--no-udn", "--out", str(out)]) == 0
    rec = json.loads((out / "inputs.json").read_text())
    frame = tifffile.imread(tmp_path / "snap0.tif")
    assert {k: rec[k] for k in ("measurement", "psf")} == input_hashes(
        frame, load_psf_any(tmp_path / "psf.tif"))
    # a second run into the same folder needs --overwrite (it would replace these files)
    assert main(["trade", "--meas", str(tmp_path / "snap0.tif"), "--psf",
                 str(tmp_path / "psf.tif"), "--quick", "--no-udn", "--out", str(out)]) == 2
