"""More bad input, found where it is read (an outside tester's findings): a truncated JPEG or an image whose header
claims 10^10 pixels, an ASCII PLY or OFF that holds fewer faces than its header declares, camera and cell files
with NaN, infinite or absurd lens values or negative seeds, a deviations CSV with a short row, an id twice or a
BOM, stations that no plan has, a plan written onto a folder, and numbers or bools written as strings. Each is one
line naming the file and the key (or line), exit 2, nothing written; the defaults of lengths a job leaves out are
physical sizes in the job's units; a UTF-8 BOM before a job file's TOML is no error."""
from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest
import trimesh

from calibration.errors import InputError, PartError
from cell.cellcal.cellfile import load_cell_file
from cell.cli import main as cell_main
from cell.jobspec import load_deviations, read_job
from jobutil import EXAMPLE, REPO, job_variant
from planning.part import load_mesh

CELL_TOML = REPO / "examples" / "cell" / "cell.toml"


def _one_error(capsys) -> str:
    err = capsys.readouterr().err
    errors = [ln for ln in err.splitlines() if ln.startswith("cell: error:")]
    assert len(errors) == 1 and "Traceback" not in err, err
    return errors[0]


def _dots_image() -> np.ndarray:
    rng = np.random.default_rng(3)
    img = np.full((480, 640), 40, np.uint8) + rng.integers(0, 4, (480, 640), dtype=np.uint8)
    for u, v in ((120, 100), (500, 120), (320, 380), (200, 300)):
        cv2.circle(img, (u, v), 9, 220, -1, lineType=cv2.LINE_AA)
    return img


def test_truncated_jpeg_is_refused_naming_the_file(tmp_path, capsys):
    ok, data = cv2.imencode(".jpg", _dots_image(), [cv2.IMWRITE_JPEG_QUALITY, 95])
    whole, cut = tmp_path / "whole.jpg", tmp_path / "cut.jpg"
    whole.write_bytes(data.tobytes())
    cut.write_bytes(data.tobytes()[: len(data) // 3])
    assert cell_main(["detect", str(whole)]) == 0
    capsys.readouterr()
    assert cell_main(["detect", str(cut)]) == 2
    line = _one_error(capsys)
    assert str(cut) in line and "truncated JPEG" in line, line


def test_image_whose_header_claims_too_many_pixels_is_refused_before_decoding(tmp_path, capsys):
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    bomb = tmp_path / "bomb.png"
    ihdr = struct.pack(">IIBBBBB", 100_000, 100_000, 8, 0, 0, 0, 0)
    bomb.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 1000))
                     + chunk(b"IEND", b""))
    assert cell_main(["detect", str(bomb)]) == 2
    line = _one_error(capsys)
    assert str(bomb) in line and "megapixels" in line and "before decoding" in line, line


def _quad_box_text(kind: str, drop: int) -> str:
    """A 100 mm cube of 6 quads (12 triangles once read) as ASCII PLY or OFF, its last ``drop`` faces cut off."""
    verts = [(x, y, z) for x in (0, 100) for y in (0, 100) for z in (0, 100)]
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    body = [" ".join(map(str, v)) for v in verts] + [f"4 {' '.join(map(str, q))}" for q in quads[: 6 - drop]]
    if kind == "ply":
        head = ["ply", "format ascii 1.0", "element vertex 8", "property float x", "property float y",
                "property float z", "element face 6", "property list uchar int vertex_indices", "end_header"]
    else:
        head = ["OFF", "# a cube", "8 6 12"]
    return "\n".join(head + body) + "\n"


@pytest.mark.parametrize("kind", ["ply", "off"])
def test_ascii_mesh_holding_fewer_faces_than_its_header_declares_is_refused(kind, tmp_path):
    whole, cut = tmp_path / f"whole.{kind}", tmp_path / f"cut.{kind}"
    whole.write_text(_quad_box_text(kind, 0))
    cut.write_text(_quad_box_text(kind, 1))
    assert len(load_mesh(whole, "mm").faces) == 12  # six quads, triangulated: the header's 6 are 6 records
    with pytest.raises(PartError) as exc:
        load_mesh(cut, "mm")
    assert str(cut) in str(exc.value) and "fewer faces than its header declares (5 of 6)" in str(exc.value)


def test_truncated_ascii_ply_part_is_refused_at_check(tmp_path, capsys):
    mesh = trimesh.load(EXAMPLE / "bracket.stl", force="mesh")
    text = mesh.export(file_type="ply", encoding="ascii").decode()
    lines = text.splitlines()
    job = job_variant(tmp_path / "job", {"job": {"mesh": "bracket.ply"}})
    (job.parent / "bracket.ply").write_text("\n".join(lines[: len(lines) - len(mesh.faces) // 2]) + "\n")
    assert cell_main(["check", str(job)]) == 2
    line = _one_error(capsys)
    assert "bracket.ply" in line and "fewer faces than its header declares" in line, line


def test_defaulted_lengths_are_physical_sizes_in_the_jobs_units(tmp_path):
    mm = read_job(job_variant(tmp_path / "mm", {"job": {"target_diameter": None, "coded_size": None}}))
    assert mm.cell.camera_box == (80.0, 80.0, 120.0)
    assert (mm.job.target_diameter, mm.job.coded_size) == (6.0, 20.0)
    um = read_job(job_variant(tmp_path / "um", {"job": {"units": "um", "target_diameter": None, "coded_size": None}}))
    assert um.cell.camera_box == pytest.approx((80_000.0, 80_000.0, 120_000.0))
    assert (um.job.target_diameter, um.job.coded_size) == pytest.approx((6000.0, 20_000.0))
    assert "camera_box" not in um.cell.model_fields_set  # a cell file's camera box still replaces it


NAN, INF = float("nan"), float("inf")
JOB_CASES = {
    "best fit on two named targets": ({"alignment": {"method": "best_fit", "targets": ["T0001", "T0002"]}},
                                      "a best fit needs at least 3"),
    "station no plan has": ({"sim": {"unreachable_stations": ["NOPE"]}}, "sim.unreachable_stations"),
    "count as a string": ({"planning": {"n_stations": "16"}}, "planning.n_stations"),
    "tolerance as a string": ({"report": {"tolerance": "0.25"}}, "report.tolerance"),
    "bool as a string": ({"camera": {"self_calibrate": "yes"}}, "camera.self_calibrate"),
    "bool as 1": ({"camera": {"self_calibrate": 1}}, "camera.self_calibrate"),
    # 250 meant in um, read in mm: the part PASSed with 0.4-0.6 mm deviations (decision 0057)
    "tolerance in another unit": ({"report": {"tolerance": 250.0}}, "a tolerance in another unit?"),
}


@pytest.mark.parametrize("case", list(JOB_CASES))
def test_bad_job_value_exits_2_at_check_naming_it(case, tmp_path, capsys):
    changes, expected = JOB_CASES[case]
    job = job_variant(tmp_path / "job", changes)
    assert cell_main(["check", str(job)]) == 2
    line = _one_error(capsys)
    assert expected in line and str(job) in line, line


DEV_CASES = {
    "short row": ("id,dx,dy,dz\nT0105,0,0.4\n", "dev.csv:2: 3 field(s)"),
    "id twice": ("id,dx,dy,dz\nT0105,0,0.4,0\nT0105,0,0,0\n", "dev.csv:3: target 'T0105' again"),
}


@pytest.mark.parametrize("case", list(DEV_CASES))
def test_bad_deviations_row_exits_2_naming_file_and_line(case, tmp_path, capsys):
    text, expected = DEV_CASES[case]
    job = job_variant(tmp_path / "job", {"sim": {"deviations": "dev.csv"}})
    (job.parent / "dev.csv").write_text(text)
    assert cell_main(["check", str(job)]) == 2
    line = _one_error(capsys)
    assert expected in line, line


def test_deviations_csv_with_a_bom_is_read(tmp_path):
    path = tmp_path / "dev.csv"
    path.write_bytes("\ufeffid,dx,dy,dz\nT2,0,0.4,0\n".encode())
    d = load_deviations(path, ["T1", "T2"], 1e-3)
    assert d[1] == pytest.approx([0, 4e-4, 0]) and not d[0].any()


CAMERA_CASES = {
    "k1 = nan": ("k1 = nan", "k1"),
    "cx_px = inf": ("cx_px = inf", "cx_px"),
    "fx_px = inf": ("fx_px = inf\nfy_px = inf", "fx_px"),
    "sigma_px = inf": ("sigma_px = inf", "sigma_px"),
    "cx_px off the image": ("cx_px = 5000.0", "cx_px"),
    "fx_px in mm": ("fx_px = 8.0\nfy_px = 8.0", "fx_px"),
    "self_calibrate = 'yes'": ('self_calibrate = "yes"', "self_calibrate"),
}


@pytest.mark.parametrize("case", list(CAMERA_CASES))
def test_camera_file_value_is_refused_when_read_naming_file_and_key(case, tmp_path, capsys):
    value, key = CAMERA_CASES[case]
    cam = tmp_path / "cam.toml"
    cam.write_text(f'[camera]\npolarity = "bright"\nwidth = 2448\nheight = 2048\n{value}\n')
    image = tmp_path / "dots.png"
    cv2.imwrite(str(image), _dots_image())
    assert cell_main(["detect", str(image), "--camera", str(cam)]) == 2
    line = _one_error(capsys)
    assert str(cam) in line and key in line, line


LENS = "fx_px = 2336.2, fy_px = 2336.2, cx_px = 1240.0, cy_px = 1012.0, k1 = -0.06"
CELL_CASES = {
    "lens cx_px nan": (LENS.replace("cx_px = 1240.0", "cx_px = nan"), "cell.camera_lens.cx_px"),
    "lens k1 nan": (LENS.replace("k1 = -0.06", "k1 = nan"), "cell.camera_lens.k1"),
    "lens fx_px inf": (LENS.replace("fx_px = 2336.2", "fx_px = inf"), "cell.camera_lens.fx_px"),
    "lens cx_px off the image": (LENS.replace("cx_px = 1240.0", "cx_px = 99999.0"), "outside the image"),
    "lens fx_px tiny": (LENS.replace("fx_px = 2336.2", "fx_px = 1e-9"), "cell.camera_lens.fx_px"),
    "hand-eye seed negative": (LENS, "hand_eye.seed"),
    "reverification seed negative": (LENS, "reverification.seed"),
}


@pytest.mark.parametrize("case", list(CELL_CASES))
def test_cell_file_value_is_refused_by_its_loader_naming_file_and_key(case, tmp_path):
    lens, expected = CELL_CASES[case]
    text = CELL_TOML.read_text()
    anchor = "flange_from_cam = { xyz = [0.0, 40.0, 90.0], rpy_deg = [0.0, 0.0, 0.0] }\n"
    text = text.replace(anchor, anchor + f"camera_lens = {{ {lens} }}\n")
    if case == "hand-eye seed negative":
        text = text.replace("seed = 3\n", "seed = -3\n")
    if case == "reverification seed negative":
        text = text.replace("seed = 5\n", "seed = -5\n")
    path = tmp_path / "cell.toml"
    path.write_text(text)
    with pytest.raises(InputError) as exc:
        load_cell_file(path)
    msg = str(exc.value)
    assert str(path) in msg and expected in msg and "\n" not in msg, msg


def test_plan_onto_a_folder_exits_2_and_writes_nothing(tmp_path, capsys):
    job = job_variant(tmp_path / "job")
    folder = tmp_path / "out" / "plan.json"
    folder.mkdir(parents=True)
    assert cell_main(["plan", str(job), "--out", str(folder)]) == 2
    line = _one_error(capsys)
    assert str(folder) in line and "folder" in line, line
    assert list((tmp_path / "out").rglob("*")) == [folder]


def test_job_file_with_a_utf8_bom_reads(tmp_path):
    job = job_variant(tmp_path / "job")
    job.write_bytes(b"\xef\xbb\xbf" + job.read_bytes())
    assert read_job(job).job.name == "bracket"
