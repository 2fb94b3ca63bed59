"""``cell detect IMAGE [--camera CAMERA.toml] [--png OUT.png]``: every detected centre of one image.

With ``--json`` one document on stdout (contract in ARCHITECTURE.md): ``image``, ``width``, ``height``,
``detections``: list of {``u``, ``v`` (px, origin at the centre of the top-left pixel), ``cov`` (2x2, px^2),
``polarity`` ("bright" | "dark"), ``code`` (int or null), ``family`` (str or null)}; plus ``noise``
(grey levels) and ``polarity`` of the image, and ``noise_levels`` ({``variance_at_zero``, ``variance_per_grey_level``}:
the pixel noise's variance as a line in the grey level, measured on the dots' tops and rings, what each ``cov``
propagated; a zero slope where the image had too few dots to measure it; decision 0047). Added (decision 0015's follow-up on over-exposed and grainy photographs): ``noise_model`` (that line in
the image's own grey levels, a dark image's being inverted first: {``variance_at_zero``, ``variance_per_grey_level``,
``constant``, ``physical``, ``note``}), ``polarity_choice`` ({``polarity``, ``counts``, ``contrast``, ``ambiguous``,
``note``} or null when the polarity was set; ambiguous is also said on stderr), ``left_out`` ([{``u``, ``v``,
``reason``}]: pieces of one dot split in two), and per detection
``clipped``, ``clipped_share`` (its rim's or top's pixels at the saturation level) and ``clipped_edge_sd_px`` (the
sd added for a heavily clipped dot's hidden edge). Ring-coded targets are reported once, at their centre dot,
with their code; the pieces of their rings are not dots and are left out. ArUco markers are reported
at the intersection of their diagonals with a covariance of (0.3 px)^2 (their corners' bias,
decision 0004).
"""
from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from pydantic import ValidationError

from calibration.dot_noise import line_in_image_levels, range_top
from calibration.dots import DetectionOptions, Detections, detect_dots, to_grey
from calibration.errors import InputError
from calibration.polarity import choose_polarity
from calibration.ringcodes import RING_FAMILIES, decode_ring_codes
from calibration.targets import detect_coded_targets
from cell.camerafile import CameraFile, load_camera_file

__all__ = ["read_image", "detect_targets", "detect_targets_chosen", "detect_image", "clipped_shares",
           "pieces_of_one_dot", "draw_detections", "detect_command"]

#: ArUco centres from the diagonals: the corners' bias (decision 0004) as a standard deviation, px
ARUCO_SIGMA_PX = 0.3
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm")
#: the smallest image side the detector takes (calibration.dots.to_grey's limit)
MIN_SIDE_PX = 8
#: the largest image read, pixels: above the largest metric cameras (151 MP) and refused from its header before decoding
#: (a PNG's header can claim 10^10 pixels in a few hundred bytes)
MAX_IMAGE_PIXELS = 160_000_000
#: a dot whose rim (dark dots: where it meets the ground) or top (bright dots) has at least this share of its pixels at
#: the image's saturation level is heavily clipped: on 15 over-exposed photographs (gain 2.5, clipped; rim shares
#: 0.84-0.99) such dots were 0.21 px rms off (0.15 px per axis) against stated sds of 0.01-0.03 px, and neither the
#: centroid nor the contour's ellipse sees it (both follow the clipped edge: their disagreement does not follow the
#: error); the originals' dots (paper at the ceiling, rims 0.34-0.63 clipped) were 0.066 px off and their
#: centroid-contour disagreement follows their error (correlation 0.8)
CLIPPED_HEAVY = 0.75
#: a heavily clipped dot's centre is said to err by this share of its radius (sd per axis) on top of the rest: what the
#: saturation hides of its edge, which the image cannot show (0.15 px per axis on dots of 4.3 px radius, above)
CLIPPED_EDGE_SD = 0.035


def read_image(path: str | Path) -> np.ndarray:
    """An image file as OpenCV reads it, unchanged (8 or 16 bit, grey or BGR); InputError if unreadable."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: image not found")
    _refuse_by_header(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{path}: not an image OpenCV can read (PNG, TIFF, JPEG, ...)")
    if img.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{path}: {img.dtype} pixels; detection needs 8- or 16-bit integer images")
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3, 4)):
        raise InputError(f"{path}: an image of shape {img.shape}; detection needs grey, BGR or BGRA pixels")
    if min(img.shape[:2]) < MIN_SIDE_PX:
        raise InputError(f"{path}: {img.shape[1]}x{img.shape[0]} pixels; detection needs at least "
                         f"{MIN_SIDE_PX}x{MIN_SIDE_PX}")
    return img


def _refuse_by_header(path: Path) -> None:
    """InputError when the file's header claims more than :data:`MAX_IMAGE_PIXELS` (refused before decoding: OpenCV
    would stop at its own limit with an assertion, or allocate it) or a JPEG stops before its end-of-image marker
    (libjpeg decodes the missing rows as grey and only warns, so the detector would find dots that are not there)."""
    from PIL import Image, UnidentifiedImageError

    size = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                size, fmt = im.size, im.format
    except Image.DecompressionBombError:
        raise InputError(f"{path}: its header claims more than {2 * Image.MAX_IMAGE_PIXELS / 1e6:.0f} megapixels; "
                         f"refused before decoding (detection takes at most {MAX_IMAGE_PIXELS / 1e6:.0f})") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
        return  # not for Pillow: OpenCV says whether it can read it
    if size[0] * size[1] > MAX_IMAGE_PIXELS:
        raise InputError(f"{path}: its header claims {size[0]}x{size[1]} pixels ({size[0] * size[1] / 1e6:.0f} "
                         f"megapixels); refused before decoding (detection takes at most {MAX_IMAGE_PIXELS / 1e6:.0f})")
    if fmt == "JPEG" and not _jpeg_reaches_eoi(path.read_bytes()):
        raise InputError(f"{path}: a truncated JPEG (the file ends before its end-of-image marker: a copy or "
                         f"transfer cut short); its missing rows would be read as grey")


def _jpeg_reaches_eoi(data: bytes) -> bool:
    """Whether a JPEG's markers, walked from SOI through every segment and entropy-coded scan, reach EOI (FFD9).
    Bytes after EOI (some cameras append data) are allowed; an EOI inside an EXIF thumbnail does not count."""
    pos, n = 2, len(data)
    while pos + 4 <= n:
        if data[pos] != 0xFF:
            return False
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker == 0xD9:
            return True
        if marker in (0x01, *range(0xD0, 0xD8)):  # no length
            pos += 2
            continue
        pos += 2 + int.from_bytes(data[pos + 2:pos + 4], "big")
        if marker != 0xDA:
            continue
        while True:  # entropy-coded data: FF00 is a stuffed FF, FFD0-D7 restart markers, FFFF fill
            pos = data.find(b"\xff", pos)
            if pos < 0 or pos + 1 >= n:
                return False
            nxt = data[pos + 1]
            if nxt == 0x00 or 0xD0 <= nxt <= 0xD7 or nxt == 0xFF:
                pos += 1 if nxt == 0xFF else 2
                continue
            break
    return pos + 1 < n and data[pos] == 0xFF and data[pos + 1] == 0xD9


def detection_options(cam: CameraFile) -> DetectionOptions:
    return DetectionOptions.for_real_images(polarity=cam.polarity)


def detect_targets(image: np.ndarray, cam: CameraFile):
    """Dots and coded targets of one image: :func:`detect_targets_chosen` without the polarity's choice."""
    return detect_targets_chosen(image, cam)[:5]


def detect_targets_chosen(image: np.ndarray, cam: CameraFile, outline: bool = False):
    """Dots and coded targets of one image, and how the polarity was chosen.

    Returns ``(det, code, keep, aruco_ids, aruco_centres)``: the detections, each one's ring code (-1: none),
    which of them are targets (not pieces of a code ring, not inside an ArUco marker), and the ArUco
    markers found. With ring codes and ``polarity = "auto"`` both polarities are tried and the one that
    reads more codes is kept: the blob count that decides otherwise can be won by a cluttered room
    around a small sheet (decision 0015). A sixth item: the :class:`calibration.polarity.PolarityChoice` (None when
    the camera file or ``--polarity`` set it). ``outline``: each dot's contour too (``Detections.centroid_shift``).
    """
    from cell.stages.imaging import MARKER_GROW, inside_any

    opts = replace(detection_options(cam), outline=outline)
    choice = None
    if opts.polarity == "auto":  # what detect_dots would choose, kept to be said
        choice = choose_polarity(to_grey(image), opts.threshold_sigma)
        opts = replace(opts, polarity=choice.polarity)
    det = detect_dots(image, opts)
    ids, centres = np.zeros(0, dtype=int), np.zeros((0, 2))
    code = np.full(len(det), -1)
    keep = np.ones(len(det), dtype=bool)
    if cam.coded_family in RING_FAMILIES:
        rc = decode_ring_codes(image, det, cam.coded_family)
        if cam.polarity == "auto":
            other = detect_dots(image, replace(opts, polarity="dark" if det.polarity == "bright" else "bright"))
            rc_other = decode_ring_codes(image, other, cam.coded_family)
            n_codes = sorted((len(rc), len(rc_other)))
            if len(rc_other) > len(rc):
                det, rc = other, rc_other
                code = np.full(len(det), -1)
                keep = np.ones(len(det), dtype=bool)
            if choice is not None and n_codes[0] != n_codes[1]:  # the codes decided: said, no longer ambiguous
                choice = replace(choice, polarity=det.polarity, ambiguous=False,
                                 note=f"{det.polarity}: it reads more ring codes ({n_codes[1]} against {n_codes[0]}); "
                                      f"the blobs said: {choice.note}")
        keep &= ~rc.ring_parts(det.uv)
        code[rc.index] = rc.code
        keep[rc.index] = True
    elif cam.coded_family == "aruco":
        ids, corners, centres = detect_coded_targets(image)
        keep &= ~inside_any(det.uv, corners, grow=MARKER_GROW)
    return det, code, keep, ids, centres, choice


def detect_image(image: np.ndarray, cam: CameraFile, report: dict | None = None) -> tuple[Detections, list[dict]]:
    """Detect the dots and coded targets of one image; returns the dots and the contract's detection list.

    Each dot also carries ``clipped`` / ``clipped_share`` (:func:`clipped_shares`); a clipped dot's ``cov`` has the
    disagreement of its two centres (by its light and by its contour's ellipse, decision 0051) added; a dot whose
    clipped share reaches :data:`CLIPPED_HEAVY` also :data:`CLIPPED_EDGE_SD` of its radius (``clipped_edge_sd_px``);
    (as does a clipped dot whose contour could not be fitted); pieces of one dot (:func:`pieces_of_one_dot`) are left
    out.
    ``report`` (a dict) receives ``polarity_choice`` and ``left_out`` ([{``u``, ``v``, ``reason``}])."""
    det, code, keep, ids, centres, choice = detect_targets_chosen(image, cam, outline=True)
    out: list[dict] = []
    left: list[dict] = []
    if cam.coded_family == "aruco":
        for i, c in zip(ids, centres):
            out.append({"u": float(c[0]), "v": float(c[1]), "cov": (ARUCO_SIGMA_PX**2 * np.eye(2)).tolist(),
                        "polarity": det.polarity, "code": int(i), "family": "aruco"})
    share = clipped_shares(image, det)
    pieces = pieces_of_one_dot(image, det, keep & (code < 0))
    for i in np.flatnonzero(keep):
        coded = code[i] >= 0
        uv = (float(det.uv[i, 0]), float(det.uv[i, 1]))
        cov = np.array(det.cov[i], dtype=float)
        if pieces[i] >= 0:
            left.append({"u": uv[0], "v": uv[1], "reason": f"a piece of one dot split in two (with the blob at "
                         f"{det.uv[pieces[i], 0]:.1f}, {det.uv[pieces[i], 1]:.1f}: no ground between them; a dot whose "
                         "middle is lighter than its rim)"})
            continue
        edge_sd = 0.0
        d = det.centroid_shift[i] if det.centroid_shift is not None else np.full(2, np.nan)
        if share[i] >= CLIPPED_HEAVY or (share[i] > 0 and not np.all(np.isfinite(d))):
            # what the saturation hides of its edge (or a clipped dot whose contour could not be fitted to check its
            # centre): stated, the image cannot show it
            radius = float(np.mean(2.0 * np.sqrt(np.clip(np.linalg.eigvalsh(det.axes[i]), 0, None))))
            edge_sd = CLIPPED_EDGE_SD * radius if np.isfinite(radius) else float("nan")
            if not np.isfinite(edge_sd):
                left.append({"u": uv[0], "v": uv[1], "reason": f"clipped ({share[i]:.0%}) and of no measurable size"})
                continue
            cov = cov + edge_sd**2 * np.eye(2)
        if share[i] > 0 and np.all(np.isfinite(d)):  # its two centres' disagreement: what the clip moved (0051)
            cov = cov + np.outer(d, d)
        out.append({"u": uv[0], "v": uv[1], "cov": cov.tolist(), "polarity": det.polarity,
                    "code": int(code[i]) if coded else None, "family": cam.coded_family if coded else None,
                    "clipped": bool(share[i] > 0), "clipped_share": round(float(share[i]), 3),
                    "clipped_edge_sd_px": round(edge_sd, 4)})
    if report is not None:
        report["polarity_choice"] = None if choice is None else choice.as_dict()
        report["left_out"] = left
    return det, out


def clipped_shares(image: np.ndarray, det: Detections) -> np.ndarray:
    """(k,) the share of each dot's pixels at the image's saturation level (any colour channel at the top of its
    grey range: 255 for 8 bits): for a dark dot those of its rim (0.85-1.5 of its ellipse's radius, where it meets a
    ground that may be clipped: an over-exposed sheet cuts the dot's edge there), for a bright one those of its top
    (within its ellipse)."""
    k = len(det)
    share = np.zeros(k)
    if k == 0:
        return share
    chans = image.reshape(image.shape[0], image.shape[1], -1)[..., :3]
    top = 255 if image.dtype == np.uint8 else range_top(float(chans.max()))
    clip = (chans >= top).any(axis=2)
    if not clip.any():
        return share
    lo, hi = (0.85, 1.5) if det.polarity == "dark" else (0.0, 1.0)
    H, W = clip.shape
    for i in range(k):
        A = det.axes[i]
        if not np.all(np.isfinite(A)) or np.linalg.eigvalsh(A).min() <= 0:
            continue
        Ai = np.linalg.inv(A) / 4.0  # the ellipse x^T axes^-1 x = 4 at rho = 1
        R = int(np.ceil(2.0 * np.sqrt(np.linalg.eigvalsh(A).max()) * hi)) + 1
        x0, y0 = int(round(det.uv[i, 0])), int(round(det.uv[i, 1]))
        ys, xs = np.mgrid[max(y0 - R, 0):min(y0 + R + 1, H), max(x0 - R, 0):min(x0 + R + 1, W)]
        dx, dy = xs - det.uv[i, 0], ys - det.uv[i, 1]
        rho = np.sqrt(np.maximum(Ai[0, 0] * dx * dx + 2 * Ai[0, 1] * dx * dy + Ai[1, 1] * dy * dy, 0.0))
        m = (rho >= lo) & (rho <= hi)
        if m.any():
            share[i] = float(clip[ys[m], xs[m]].mean())
    return share


def pieces_of_one_dot(image: np.ndarray, det: Detections, among: np.ndarray) -> np.ndarray:
    """(k,) for each dot of ``among`` that is a piece of one dot with another, the other's index; else -1.

    A dot whose middle is lighter than its rim (a printed dot with a pale centre; an over-exposed one) can be cut in
    two by the detector's local half-maximum: two blobs within a few of their radii, with no ground between them (the
    profile between their centres stays above their ground by a quarter of the smaller's peak), or whose ellipses
    overlap (centres closer than the sum of their radii: an over-exposed dot's clipped middle is at the ground's own
    level); the two of comparable depth (a speck of dirt by a dot is not its piece). Two dots never are."""
    k = len(det)
    other = np.full(k, -1)
    idx = np.flatnonzero(among)
    if len(idx) < 2:
        return other
    grey = to_grey(image)
    work = (grey if det.polarity == "bright" else cv2.bitwise_not(grey)).astype(np.float32)  # as the detector saw it
    r = 2.0 * np.sqrt(np.clip(np.linalg.eigvalsh(det.axes[idx]), 0, None)).mean(axis=1)
    from scipy.spatial import cKDTree

    tree = cKDTree(det.uv[idx])
    for a, b in sorted(tree.query_pairs(3.0 * max(float(r.max()), 1.0))):
        i, j = idx[a], idx[b]
        d = float(np.linalg.norm(det.uv[i] - det.uv[j]))
        if d > 2.0 * (r[a] + r[b]) + 2.0:
            continue
        t = np.linspace(0.0, 1.0, max(int(np.ceil(2 * d)), 3))
        p = det.uv[i][None] + t[:, None] * (det.uv[j] - det.uv[i])[None]
        prof = cv2.remap(work, p[:, 0].astype(np.float32)[None], p[:, 1].astype(np.float32)[None],
                         cv2.INTER_LINEAR)[0]
        ground = max(det.background[i], det.background[j])
        if min(det.peak[i], det.peak[j]) < 0.4 * max(det.peak[i], det.peak[j]):  # a speck by a dot, not its piece
            continue
        if d < r[a] + r[b] or prof.min() - ground > 0.25 * min(det.peak[i], det.peak[j]):
            other[i], other[j] = j, i
    return other


def draw_detections(image: np.ndarray, detections: list[dict]) -> np.ndarray:
    """An 8-bit colour copy of ``image`` with each centre marked (green dots, orange coded targets + code)."""
    img = image
    if img.dtype == np.uint16:
        img = cv2.convertScaleAbs(img, alpha=255.0 / max(int(img.max()), 1))
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    img = img.copy()
    scale = max(1, int(round(max(img.shape[:2]) / 1500)))
    for d in detections:
        p = (int(round(d["u"] * 16)), int(round(d["v"] * 16)))
        if d["code"] is None:
            cv2.circle(img, p, 6 * 16 * scale, (0, 200, 0), scale, cv2.LINE_AA, shift=4)
        else:
            cv2.circle(img, p, 10 * 16 * scale, (0, 140, 255), 2 * scale, cv2.LINE_AA, shift=4)
            cv2.putText(img, str(d["code"]), (int(d["u"]) + 12 * scale, int(d["v"]) - 12 * scale),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, (0, 140, 255), 2 * scale, cv2.LINE_AA)
    return img


def detect_command(args, out) -> int:
    cam = load_camera_file(args.camera)
    over = {k: v for k, v in (("polarity", getattr(args, "polarity", None)), ("coded_family", getattr(args, "family", None)))
            if v is not None}
    if over:
        try:
            cam = CameraFile(**(cam.model_dump() | over))
        except ValidationError as e:
            err = e.errors()[0]
            raise InputError(f"cell detect: --{'family' if err['loc'][0] == 'coded_family' else err['loc'][0]}: "
                             f"{err['msg']}") from None
    image = read_image(args.image)
    report: dict = {}
    det, dets = detect_image(image, cam, report)
    grey_top = 255.0 if image.dtype == np.uint8 else 65535.0  # what the dark image's inversion subtracted from
    doc = {"image": str(args.image), "width": int(image.shape[1]), "height": int(image.shape[0]),
           "polarity": det.polarity, "noise": float(det.noise),
           "noise_levels": None if det.noise_levels is None else
           {"variance_at_zero": det.noise_levels[0], "variance_per_grey_level": det.noise_levels[1]},
           # the same line in the image's own grey levels (a dark dot's image is inverted before it is measured),
           # whether it has photon noise's shape, or the one figure used instead and why
           "noise_model": line_in_image_levels(det.noise_levels, det.polarity, grey_top, float(det.noise)),
           "polarity_choice": report["polarity_choice"],
           "left_out": report["left_out"],
           "detections": dets}
    if args.png is not None:
        png = Path(args.png)
        if png.suffix.lower() != ".png":
            raise InputError(f"--png {png}: give a .png file name")
        tmp = png.with_name(png.name + ".part.png")
        if not cv2.imwrite(str(tmp), draw_detections(image, dets)):
            raise InputError(f"--png {png}: cannot write there")
        tmp.replace(png)

    def human(d):
        n_coded = sum(1 for x in d["detections"] if x["code"] is not None)
        out.say(f"{d['image']}: {d['width']}x{d['height']}, {d['polarity']} dots, noise {d['noise']:.2f} grey levels: "
                f"{len(d['detections']) - n_coded} dots, {n_coded} coded targets")
        pc = d.get("polarity_choice")
        if pc and pc["ambiguous"]:
            out.say(f"  WARNING polarity ambiguous: {pc['note']} (--polarity or the camera file's polarity settles it)")
        nm = d.get("noise_model")
        if nm and nm["variance_at_zero"] is not None:  # the line the covariances propagated (decision 0047)
            if nm["constant"]:
                out.say(f"  pixel noise: {nm['note']}")
            else:
                out.say(f"  pixel noise variance {nm['variance_at_zero']:.3f} + {nm['variance_per_grey_level']:.4f} x "
                        f"grey level ({nm['note']})")
            if not nm["physical"]:
                out.say("  WARNING the pixel noise's line is not photon noise's shape: the stated sds rest on it")
        n_clip = sum(1 for x in d["detections"] if x.get("clipped"))
        if n_clip:
            n_heavy = sum(1 for x in d["detections"] if x.get("clipped_share", 0) >= CLIPPED_HEAVY)
            n_edge = sum(1 for x in d["detections"] if x.get("clipped_edge_sd_px"))
            out.say(f"  {n_clip} dots touch the saturation level: flagged (clipped_share), their sd includes the "
                    "disagreement of their two centres (light and contour)"
                    + (f"; {n_edge} ({n_heavy} heavily clipped, >= {CLIPPED_HEAVY:.0%}; the rest without a "
                       f"contour) also {CLIPPED_EDGE_SD:.1%} of their radius for the edge the saturation hides"
                       if n_edge else ""))
            if n_heavy:
                out.say(f"  WARNING {n_heavy} dots heavily clipped: the image is over-exposed where they are")
        if d.get("left_out"):
            why: dict[str, int] = {}
            for x in d["left_out"]:
                key = x["reason"].split(":")[0].split(" (")[0]
                why[key] = why.get(key, 0) + 1
            out.say(f"  WARNING {len(d['left_out'])} blobs left out: " + ", ".join(f"{n} {k}" for k, n in why.items())
                    + " (left_out in the JSON says where and why)")
        if not out.as_json:
            for x in d["detections"]:
                sd = np.sqrt(np.diag(np.asarray(x["cov"])))
                tag = f"  code {x['code']} ({x['family']})" if x["code"] is not None else ""
                print(f"{x['u']:10.3f} {x['v']:10.3f}  sd {sd[0]:.3f} {sd[1]:.3f} px{tag}")

    out.result(doc, human)
    return 0
