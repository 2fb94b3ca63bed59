"""``cell detect``: one image's centres as the contract's JSON, a drawing, and one-line errors."""
from __future__ import annotations

import json

import cv2
import numpy as np

from cell.cli import main
from tests.test_targets import grid_uv, render_dots


def test_detect_prints_every_dot_of_a_16_bit_dark_image_as_the_contract_says(tmp_path, capsys):
    rng = np.random.default_rng(5)
    uv = grid_uv(rng, 240, 320, 8, 6)
    img = (65535 - render_dots(rng, 240, 320, uv, radius_px=4.0, bits=16)).astype(np.uint16)
    path = tmp_path / "sheet.tif"
    cv2.imwrite(str(path), img)
    cam = tmp_path / "camera.toml"
    cam.write_text('[camera]\npolarity = "dark"\ncoded_family = "ring12"\n')
    png = tmp_path / "drawn.png"
    assert main(["detect", str(path), "--camera", str(cam), "--json", "--png", str(png)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert (doc["width"], doc["height"]) == (320, 240)
    dets = doc["detections"]
    assert len(dets) == len(uv)
    found = np.array([[d["u"], d["v"]] for d in dets])
    err = np.min(np.linalg.norm(found[:, None] - uv[None], axis=2), axis=1)
    assert err.max() < 0.05
    for d in dets:
        assert d["polarity"] == "dark" and d["code"] is None and d["family"] is None
        cov = np.asarray(d["cov"])
        assert cov.shape == (2, 2) and np.all(np.linalg.eigvalsh(cov) > 0)
    drawn = cv2.imread(str(png))
    assert drawn.shape == (240, 320, 3)
    # the pixel noise's line the covariances propagated (decision 0047), in the document and said to a person
    assert set(doc["noise_levels"]) == {"variance_at_zero", "variance_per_grey_level"}
    assert main(["detect", str(path), "--camera", str(cam)]) == 0
    said = capsys.readouterr()
    assert "pixel noise" in said.out + said.err


def test_detect_refuses_what_it_cannot_read_with_exit_2(tmp_path, capsys):
    bad = tmp_path / "notes.png"
    bad.write_text("not an image")
    assert main(["detect", str(bad)]) == 2
    assert "not an image" in capsys.readouterr().err
    cam = tmp_path / "camera.toml"
    cam.write_text('[camera]\npolarity = "sideways"\n')
    img = tmp_path / "a.png"
    cv2.imwrite(str(img), np.zeros((20, 20), np.uint8))
    assert main(["detect", str(img), "--camera", str(cam)]) == 2
    assert "[camera] polarity" in capsys.readouterr().err


def test_detect_options_override_the_camera_file(tmp_path, capsys):
    rng = np.random.default_rng(7)
    uv = grid_uv(rng, 120, 160, 4, 3)
    img = 255 - render_dots(rng, 120, 160, uv, radius_px=3.5)
    path = tmp_path / "dots.png"
    cv2.imwrite(str(path), img)
    assert main(["detect", str(path), "--polarity", "bright", "--json"]) == 0
    bright = json.loads(capsys.readouterr().out)
    assert main(["detect", str(path), "--polarity", "dark", "--json"]) == 0
    dark = json.loads(capsys.readouterr().out)
    assert dark["polarity"] == "dark" and len(dark["detections"]) == len(uv)
    assert bright["polarity"] == "bright" and len(bright["detections"]) < len(uv)
    assert main(["detect", str(path), "--family", "nope"]) == 2
    assert "--family" in capsys.readouterr().err
