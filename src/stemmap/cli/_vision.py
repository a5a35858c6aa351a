"""``stemmap calibrate | segment | fuse``: laser-camera calibration, trunk segmentation, fusion.

File formats
------------
Correspondence CSV (calibrate): header ``x,y,u,v`` (laser metres, image pixels; Xue 2018 §3.1)
or ``x,y,z,u,v`` (3D sensor points, for PnP). Lines starting with ``#`` are comments.

Calibration JSON (written by calibrate, read by fuse): ``G`` (3x3, laser plane -> pixels),
``method``, ``rms_px``, ``n_pairs``, ``n_inliers``, ``residuals_px``; with intrinsics given also
``camera`` {``K``, ``width``, ``height``, optional ``dist`` = OpenCV (k1, k2, p1, p2[, k3]),
used to undistort image regions before edge diameters} and, for PnP, ``laser_to_camera``
{``R``, ``t``}.

RoI CSV (segment --rois): ``x,y,w,h,alpha`` per region (pixels; alpha of Xue eq. 18).

Decisions CSV (fuse): ``kind,laser_index,region_index,x,y,width,mT,mNT,mTheta,conflict,is_trunk``.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
import typer
from rich.markup import escape
from rich.table import Table

from stemmap.cli._common import console, fail_on_stemmap_error, out
from stemmap.cli._validate import bounded
from stemmap.errors import ConfigError, InputError
from stemmap.io._util import existing_file
from stemmap.io.atomic import atomic_write
from stemmap.io.products import run_products

__all__ = ["calibrate", "fuse", "overlay_image", "read_calibration", "register", "segment"]


def _read_table(path: Path, required: list[str], optional: list[str]) -> dict[str, np.ndarray]:
    existing_file(path, "correspondence CSV")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read {path}: {exc}") from exc
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputError(f"{path} is empty; expected a header line {','.join(required)}.")
    rows = list(csv.reader(io.StringIO("\n".join(lines))))
    header = [h.strip() for h in rows[0]]
    missing = [c for c in required if c not in header]
    if missing:
        raise InputError(
            f"{path} lacks column(s) {', '.join(missing)}; its header is {','.join(header)}."
        )
    data = []
    for k, r in enumerate(rows[1:], start=2):
        if len(r) != len(header):
            raise InputError(f"{path}, data row {k}: {len(r)} fields for {len(header)} columns.")
        try:
            data.append([float(v) for v in r])
        except ValueError as exc:
            raise InputError(f"{path}, data row {k}: every field must be a number.") from exc
    arr = np.asarray(data, dtype=np.float64).reshape(-1, len(header))
    return {c: arr[:, header.index(c)] for c in required + optional if c in header}


def _matrix(doc: dict[str, Any], key: str, shape: tuple[int, ...], path: Path, where: str) -> Any:
    """``doc[key]`` as a finite float array of ``shape``; InputError naming the field."""
    name = f"{where}{key}"
    if key not in doc:
        raise InputError(f"calibration JSON {str(path)!r} lacks the field {name!r}.")
    try:
        a = np.asarray(doc[key], dtype=np.float64)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape != shape or not np.all(np.isfinite(a)):
        form = "x".join(str(n) for n in shape)
        raise InputError(
            f"calibration JSON {str(path)!r}: field {name!r} must be a {form} array of finite "
            f"numbers, got {str(doc[key])[:80]}."
        )
    return a


def _distortion(cam: dict[str, Any], path: Path) -> np.ndarray:
    """``camera.dist``: OpenCV's (k1, k2, p1, p2[, k3]); zeros when absent."""
    if "dist" not in cam:
        return np.zeros(5)
    try:
        d = np.asarray(cam["dist"], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        d = np.zeros(0)
    if d.shape[0] not in (4, 5) or not np.all(np.isfinite(d)):
        raise InputError(
            f"calibration JSON {str(path)!r}: 'camera.dist' must be 4 or 5 finite numbers "
            f"(OpenCV k1, k2, p1, p2[, k3]; the rational and thin-prism models are not "
            f"supported), got {str(cam['dist'])[:80]}."
        )
    return np.concatenate((d, np.zeros(5 - d.shape[0])))


def read_calibration(path: Path) -> dict[str, Any]:
    """Read and check a calibration JSON written by ``stemmap calibrate`` (see module doc).

    Every field the fusion uses is checked here, so a damaged or hand-edited file ends in one
    error naming the field (never a KeyError): ``G`` 3x3 finite and invertible (an all-zero or
    singular matrix maps every laser point to nowhere); optional ``camera`` with ``K`` 3x3
    (positive focal lengths), positive integer ``width``/``height`` and optional lens
    distortion ``dist`` (OpenCV k1, k2, p1, p2[, k3]; ``camera`` is returned as
    ``(K, width, height, dist)``, the arguments of ``CameraModel``); optional
    ``laser_to_camera`` with a rotation ``R`` (orthonormal, det +1) and a 3-vector ``t``.
    """
    if not path.exists():
        raise InputError(f"calibration JSON {str(path)!r} does not exist.")
    if path.is_dir():
        raise InputError(f"calibration JSON {str(path)!r} is a folder, not a file.")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise InputError(
            f"calibration JSON {str(path)!r} is not UTF-8 text: is it binary?"
        ) from exc
    except ValueError as exc:
        raise InputError(f"calibration JSON {str(path)!r} is not valid JSON: {exc}.") from exc
    except RecursionError:  # json's C scanner recurses per nested array or object
        raise InputError(
            f"calibration JSON {str(path)!r} nests arrays or objects too deeply."
        ) from None
    except OSError as exc:
        raise InputError(f"cannot read calibration JSON {str(path)!r}: {exc}.") from exc
    if not isinstance(doc, dict):
        raise InputError(f"calibration JSON {str(path)!r} must hold an object with a field 'G'.")
    G = _matrix(doc, "G", (3, 3), path, "")
    s = np.linalg.svd(G, compute_uv=False)
    if not s[0] > 0 or s[-1] / s[0] < 1e-12:
        raise InputError(
            f"calibration JSON {str(path)!r}: field 'G' is singular (singular values "
            f"{', '.join(f'{v:.3g}' for v in s)}); rerun `stemmap calibrate`."
        )
    out: dict[str, Any] = {"G": G}
    if "camera" in doc:
        cam = doc["camera"]
        if not isinstance(cam, dict):
            raise InputError(f"calibration JSON {str(path)!r}: field 'camera' must be an object.")
        K = _matrix(cam, "K", (3, 3), path, "camera.")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise InputError(
                f"calibration JSON {str(path)!r}: 'camera.K' focal lengths must be > 0, got "
                f"fx={K[0, 0]}, fy={K[1, 1]}."
            )
        size = []
        for key in ("width", "height"):
            v = cam.get(key)
            if v is None:
                raise InputError(f"calibration JSON {str(path)!r} lacks the field 'camera.{key}'.")
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise InputError(
                    f"calibration JSON {str(path)!r}: 'camera.{key}' must be a positive whole "
                    f"number of pixels, got {v!r}."
                )
            size.append(v)
        out["camera"] = (K, size[0], size[1], _distortion(cam, path))
    if "laser_to_camera" in doc:
        l2c = doc["laser_to_camera"]
        if not isinstance(l2c, dict):
            raise InputError(
                f"calibration JSON {str(path)!r}: field 'laser_to_camera' must be an object."
            )
        R = _matrix(l2c, "R", (3, 3), path, "laser_to_camera.")
        t = _matrix(l2c, "t", (3,), path, "laser_to_camera.")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise InputError(
                f"calibration JSON {str(path)!r}: 'laser_to_camera.R' is not a rotation matrix "
                "(R R^T != I or det R < 0)."
            )
        out["laser_to_camera"] = (R, t)
    return out


def _camera(
    fx: float | None,
    fy: float | None,
    cx: float | None,
    cy: float | None,
    width: int | None,
    height: int | None,
    dist: str | None = None,
) -> Any:
    from stemmap.vision.camera import CameraModel

    vals = (fx, cx, cy, width, height)
    if all(v is None for v in vals):
        if dist is not None:
            raise ConfigError(
                "--dist needs the camera intrinsics (--fx --cx --cy --width --height)."
            )
        return None
    if any(v is None for v in vals):
        raise ConfigError("camera intrinsics need --fx, --cx, --cy, --width and --height together.")
    d = np.zeros(5)
    if dist is not None:
        try:
            dv = [float(v) for v in dist.split(",")]
        except ValueError:
            dv = []
        if len(dv) not in (4, 5) or not all(math.isfinite(v) for v in dv):
            raise ConfigError(
                f"--dist must be 4 or 5 comma-separated numbers k1,k2,p1,p2[,k3], got {dist!r}."
            )
        d[: len(dv)] = dv
    K = np.array([[fx, 0.0, cx], [0.0, fy if fy is not None else fx, cy], [0.0, 0.0, 1.0]])
    return CameraModel(K, int(width), int(height), d)  # type: ignore[arg-type]


def calibrate(
    pairs: Annotated[Path, typer.Argument(help="Correspondence CSV: x,y,u,v or x,y,z,u,v.")],
    out_path: Annotated[Path, typer.Option("--out", "-o", help="Calibration JSON to write.")],
    method: Annotated[
        str, typer.Option(help="Homography: xue2018, dlt, dlt_refined, ransac.")
    ] = "dlt_refined",
    threshold_px: Annotated[
        float,
        typer.Option(
            help="RANSAC inlier threshold, pixels.", callback=bounded("--threshold-px", gt=0)
        ),
    ] = 3.0,
    pnp: Annotated[
        bool, typer.Option(help="Also solve the sensor-to-camera pose by PnP (needs --fx ...).")
    ] = False,
    fx: Annotated[
        float | None, typer.Option(help="Focal length x, pixels.", callback=bounded("--fx", gt=0))
    ] = None,
    fy: Annotated[
        float | None,
        typer.Option(help="Focal length y, pixels (default fx).", callback=bounded("--fy", gt=0)),
    ] = None,
    cx: Annotated[
        float | None, typer.Option(help="Principal point x, pixels.", callback=bounded("--cx"))
    ] = None,
    cy: Annotated[
        float | None, typer.Option(help="Principal point y, pixels.", callback=bounded("--cy"))
    ] = None,
    width: Annotated[
        int | None, typer.Option(help="Image width, pixels.", callback=bounded("--width", ge=1))
    ] = None,
    height: Annotated[
        int | None, typer.Option(help="Image height, pixels.", callback=bounded("--height", ge=1))
    ] = None,
    seed: Annotated[
        int, typer.Option(help="RANSAC random seed.", callback=bounded("--seed", ge=0))
    ] = 0,
    dist: Annotated[
        str | None,
        typer.Option(
            help="Lens distortion 'k1,k2,p1,p2[,k3]' (OpenCV), stored with the intrinsics; "
            "image regions are undistorted with it before edge diameters are measured."
        ),
    ] = None,
) -> None:
    """Fit the laser-to-image matrix G (and optionally the PnP pose); report pixel errors.

    Example: stemmap calibrate pairs.csv --out calib.json --method ransac
    """
    from stemmap.vision.calibrate import fit_homography, solve_pnp

    with (
        fail_on_stemmap_error(),
        run_products("calibrate", inputs=[pairs], outputs=[out_path]) as run,
    ):
        t = _read_table(pairs, ["x", "y", "u", "v"], ["z"])
        xy = np.column_stack((t["x"], t["y"]))
        uv = np.column_stack((t["u"], t["v"]))
        opts: dict[str, Any] = (
            {"threshold_px": threshold_px, "rng": seed} if method == "ransac" else {}
        )
        fit = fit_homography(xy, uv, method, **opts)
        if not fit:
            raise InputError(f"calibration of {pairs} failed: {fit.reason}.")
        doc: dict[str, Any] = {
            "G": fit.G.tolist(),
            "method": fit.method,
            "rms_px": fit.rms_px,
            "n_pairs": int(xy.shape[0]),
            "n_inliers": int(fit.inliers.sum()),
            "residuals_px": [round(float(r), 4) for r in fit.residuals_px],
        }
        cam = _camera(fx, fy, cx, cy, width, height, dist)
        if cam is not None:
            doc["camera"] = {"K": cam.K.tolist(), "width": cam.width, "height": cam.height}
            if cam.has_distortion:
                doc["camera"]["dist"] = cam.dist.tolist()
        if pnp:
            if cam is None:
                raise ConfigError(
                    "--pnp needs the camera intrinsics (--fx --cx --cy --width --height)."
                )
            z = t.get("z", np.zeros(xy.shape[0]))
            pose = solve_pnp(np.column_stack((xy, z)), uv, cam, ransac=method == "ransac")
            if not pose or pose.transform is None:
                raise InputError(f"PnP on {pairs} failed: {pose.reason}.")
            doc["laser_to_camera"] = {
                "R": pose.transform.R.tolist(),
                "t": pose.transform.t.tolist(),
                "rms_px": pose.rms_px,
            }
        with atomic_write(run.path(out_path)) as fh:
            json.dump(doc, fh, indent=2)
    table = Table(title=f"calibration ({fit.method})")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    table.add_row("pairs", str(xy.shape[0]))
    table.add_row("inliers", str(int(fit.inliers.sum())))
    table.add_row("RMS reprojection error (px)", f"{fit.rms_px:.3f}")
    table.add_row("max error (px)", f"{float(np.max(fit.residuals_px)):.3f}")
    if "laser_to_camera" in doc:
        table.add_row("PnP RMS error (px)", f"{doc['laser_to_camera']['rms_px']:.3f}")
    out.print(table)


_SEGMENT_METHODS = ("pixel", "xue2018", "xue2018_strict", "full_frame")
_IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")


def _expand(paths: list[Path], suffixes: tuple[str, ...], what: str) -> list[Path]:
    """Files given directly, or the files with one of ``suffixes`` inside given folders."""
    files: list[Path] = []
    for p in paths:
        if p.is_dir():
            files += sorted(f for f in p.iterdir() if f.suffix.lower() in suffixes)
        elif p.is_file():
            files.append(p)
        else:
            raise InputError(f"{what} {p} does not exist.")
    if not files:
        raise InputError(f"no {what} files found in {', '.join(map(str, paths))}.")
    return files


def _pair_labels(images: list[Path], labels: list[Path]) -> list[tuple[Path, Path]]:
    """Pair every training image with the label file of the same stem (.txt YOLO or mask)."""
    by_stem: dict[str, Path] = {}
    for lab in labels:
        if lab.stem in by_stem:
            raise InputError(f"two label files for {lab.stem!r}: {by_stem[lab.stem]} and {lab}.")
        by_stem[lab.stem] = lab
    pairs = []
    for im in images:
        if im.stem not in by_stem:
            raise InputError(
                f"no label file named {im.stem}.txt (YOLO polygons) or {im.stem}.png (mask) "
                f"for training image {im}."
            )
        pairs.append((im, by_stem[im.stem]))
    return pairs


def _encode(path: Path, img: np.ndarray) -> bytes:
    ext = path.suffix.lower() if path.suffix.lower() in (".png", ".jpg", ".jpeg") else ".png"
    ok, buf = cv2.imencode(ext, img)
    if not ok:  # pragma: no cover - OpenCV failure
        raise InputError(f"could not encode the image for {path}.")
    return bytes(buf.tobytes())


def overlay_image(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """BGR picture of the photo with the trunk mask in translucent red and its outline."""
    bgr = np.ascontiguousarray(rgb[..., ::-1]).copy()
    m = mask.astype(bool)
    bgr[m] = (0.45 * bgr[m] + 0.55 * np.array([40, 40, 255])).astype(np.uint8)
    contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(bgr, contours, -1, (0, 0, 255), max(1, round(rgb.shape[1] / 640)))
    return bgr


def _train_segmenter(
    train: list[Path],
    labels: list[Path],
    model_out: Path,
    max_pixels: int,
    settings: dict[str, Any],
) -> str:
    from stemmap.vision.image_io import read_image
    from stemmap.vision.segment_classifier import (
        read_label_mask,
        save_model,
        train_pixel_classifier,
    )

    pairs = _pair_labels(
        _expand(train, _IMAGE_SUFFIXES, "training image"),
        _expand(labels, (".txt", ".png", ".bmp"), "label"),
    )
    imgs, masks = [], []
    for im, lab in pairs:
        rgb = read_image(im, max_pixels=max_pixels)
        imgs.append(rgb)
        masks.append(read_label_mask(lab, rgb.shape[1], rgb.shape[0]))
    meta = {"trained_on": [im.name for im, _ in pairs]}
    model = train_pixel_classifier(imgs, masks, meta=meta, **settings)
    save_model(model, model_out)
    return f"trained on {len(pairs)} image(s) ({model.trees.n_nodes} tree nodes)"


def segment(
    image: Annotated[
        Path | None, typer.Argument(help="Colour image (PNG, JPEG, BMP) to segment.")
    ] = None,
    out_path: Annotated[
        Path | None, typer.Option("--out", "-o", help="Mask PNG to write (0 / 255).")
    ] = None,
    rois: Annotated[
        Path | None, typer.Option(help="Also write the regions: x,y,w,h,alpha CSV.")
    ] = None,
    overlay: Annotated[
        Path | None,
        typer.Option(help="Also write the photo with the mask drawn over it (PNG or JPEG)."),
    ] = None,
    method: Annotated[
        str,
        typer.Option(
            help="pixel: trainable pixel classifier (default model: the shipped mangrove one, "
            "or --model). xue2018: Xue 2018's stripping segmentation (RGB rules); it CROPS THE "
            "TOP 25 % of the image (canopy) and keeps only regions taller than wide. "
            "xue2018_strict: without our green-plant rule. full_frame: Xue without the crop."
        ),
    ] = "pixel",
    preset: Annotated[
        str | None, typer.Option(help="Alias of --method for the Xue presets (older scripts).")
    ] = None,
    model: Annotated[
        Path | None, typer.Option(help="Pixel-classifier model (.npz from --model-out).")
    ] = None,
    train: Annotated[
        list[Path] | None,
        typer.Option(
            metavar="IMAGES",
            help="Train a pixel classifier on these images or folders (repeatable).",
        ),
    ] = None,
    labels: Annotated[
        list[Path] | None,
        typer.Option(
            metavar="LABELS",
            help="Training labels, files or folders: YOLO polygon .txt (class 0 = trunk; all "
            "class-0 polygons of a file form one trunk mask, other classes are ignored) or "
            "mask PNG (nonzero = trunk), matched to the images by file name stem.",
        ),
    ] = None,
    model_out: Annotated[
        Path | None, typer.Option(help="Where --train writes the model (.npz, no pickle).")
    ] = None,
    work_width: Annotated[
        int, typer.Option(help="Training: feature resolution (image width, pixels).")
    ] = 384,
    augment: Annotated[
        int,
        typer.Option(
            help="Training: random-camera copies per training image (white balance, exposure, "
            "tone, hue, blur, JPEG) so the model holds under other cameras; 0 = none."
        ),
    ] = 4,
    colour_norm: Annotated[
        str,
        typer.Option(
            help="Training: per-image colour normalisation stored in the model (none | grey_world)."
        ),
    ] = "grey_world",
    threshold: Annotated[
        float, typer.Option(help="Training: P(trunk) threshold stored in the model.")
    ] = 0.5,
    open_px: Annotated[
        int, typer.Option(help="Training: opening (pixels at the working width) in the model.")
    ] = 3,
    min_area: Annotated[
        float,
        typer.Option(help="Training: drop components below this fraction of the image."),
    ] = 2e-3,
    max_pixels: Annotated[
        int,
        typer.Option(help="Refuse images with more pixels than this (read from the header)."),
    ] = 100_000_000,
) -> None:
    """Segment trunks in a photo (mask, regions, overlay), or train a pixel classifier.

    Examples:
    stemmap segment photo.jpg --out mask.png --overlay overlay.jpg;
    stemmap segment frame.png --out mask.png --method xue2018 --rois rois.csv;
    stemmap segment --train photos/ --labels labels/ --model-out trunks.npz;
    stemmap segment photo.jpg --model trunks.npz --out mask.png
    """
    from stemmap.vision.image_io import read_image
    from stemmap.vision.segment import segment_trunks
    from stemmap.vision.segment_classifier import default_model, load_model, segment_pixels

    if train is not None or labels is not None or model_out is not None:
        with (
            fail_on_stemmap_error(),
            run_products(
                "segment", inputs=[*(train or []), *(labels or [])], outputs=[model_out]
            ) as run,
        ):
            if not train or not labels or model_out is None:
                raise ConfigError("training needs --train IMAGES, --labels LABELS and --model-out.")
            if image is not None:
                raise ConfigError(
                    f"give either an image to segment ({image}) or --train, not both."
                )
            settings = {
                "work_width": work_width,
                "augment": augment,
                "colour_norm": colour_norm,
                "threshold": threshold,
                "open_px": open_px,
                "min_area_frac": min_area,
            }
            msg = _train_segmenter(train, labels, run.path(model_out), max_pixels, settings)
        out.print(f"{msg} -> {model_out}")
        return
    with (
        fail_on_stemmap_error(),
        run_products("segment", inputs=[image, model], outputs=[out_path, rois, overlay]) as run,
    ):
        if image is None or out_path is None:
            raise ConfigError("segment needs an IMAGE and --out MASK (or --train ... to train).")
        meth = preset if preset is not None else method
        if meth not in _SEGMENT_METHODS:
            raise ConfigError(
                f"--method must be one of {', '.join(_SEGMENT_METHODS)}, got {meth!r}."
            )
        if model is not None and meth != "pixel":
            raise ConfigError(f"--model is for --method pixel, not {meth!r}.")
        rgb = read_image(image, max_pixels=max_pixels)
        if meth == "pixel":
            seg = segment_pixels(rgb, load_model(model) if model else default_model())
        else:
            seg = segment_trunks(rgb, meth)
        with atomic_write(run.path(out_path), "wb") as fh:
            fh.write(_encode(out_path.with_suffix(".png"), seg.mask.astype(np.uint8) * 255))
        if overlay is not None:
            with atomic_write(run.path(overlay), "wb") as fh:
                fh.write(_encode(overlay, overlay_image(rgb, seg.mask)))
        if rois is not None:
            with atomic_write(run.path(rois)) as fh:
                w = csv.writer(fh, lineterminator="\n")
                w.writerow(["x", "y", "w", "h", "alpha"])
                r = seg.regions
                for k in range(len(r)):
                    w.writerow(
                        [int(r.x[k]), int(r.y[k]), int(r.w[k]), int(r.h[k]), f"{r.alpha[k]:.4f}"]
                    )
    out.print(f"{len(seg.regions)} trunk region(s) ({meth}); mask written to {out_path}")


def fuse(
    scan: Annotated[Path, typer.Option(help="Scan file (.npz, .csv, bag) read by stemmap.io.")],
    image: Annotated[Path, typer.Option(help="The camera image taken with the scan.")],
    calibration: Annotated[Path, typer.Option(help="Calibration JSON from `stemmap calibrate`.")],
    out_path: Annotated[Path, typer.Option("--out", "-o", help="Decisions CSV to write.")],
    scan_index: Annotated[
        int,
        typer.Option(
            help="Which scan of the file (0-based).", callback=bounded("--scan-index", ge=0)
        ),
    ] = 0,
    method: Annotated[str, typer.Option(help="xue2018 or ours.")] = "xue2018",
    bpa: Annotated[
        str, typer.Option(help="BPA preset: xue2018, xue2018_printed, forest.")
    ] = "xue2018",
    preset: Annotated[
        str,
        typer.Option(
            help="Segmentation preset of the image regions: xue2018 (the paper's rules; crops "
            "the top 25 % of the image), xue2018_strict (without our green-plant rule) or "
            "full_frame (no crop)."
        ),
    ] = "xue2018",
) -> None:
    """Fuse one laser scan with one image: laser RoIs + stripping segmentation + Dempster-Shafer.

    ``ours`` needs the camera intrinsics in the calibration JSON (calibrate --fx ...).

    Example: stemmap fuse --scan run.npz --image frame.png --calibration calib.json --out d.csv
    """
    from stemmap.fusion.associate import laser_rois
    from stemmap.fusion.fuse import FusionParams, fuse_ours, fuse_xue2018
    from stemmap.io.scans import read_scans
    from stemmap.vision.camera import CameraModel, RigidTransform
    from stemmap.vision.image_io import read_image
    from stemmap.vision.segment import segment_trunks

    with (
        fail_on_stemmap_error(),
        run_products("fuse", inputs=[scan, image, calibration], outputs=[out_path]) as run,
    ):
        if method not in ("xue2018", "ours"):
            raise ConfigError(f"--method must be 'xue2018' or 'ours', got {method!r}.")
        doc = read_calibration(calibration)
        G = doc["G"]
        batch = read_scans(scan)
        if not 0 <= scan_index < len(batch):
            raise InputError(
                f"{scan} has {len(batch)} scan(s); --scan-index {scan_index} is out of range."
            )
        rgb = read_image(image)  # header pixel limit and truncation checks, as in segment
        if "camera" in doc and (rgb.shape[1], rgb.shape[0]) != doc["camera"][1:3]:
            cw, ch = doc["camera"][1:3]
            raise InputError(
                f"image {str(image)!r} is {rgb.shape[1]} x {rgb.shape[0]} pixels but the "
                f"calibration {str(calibration)!r} is for a {cw} x {ch} camera: G and the "
                "intrinsics hold only at that size; resize the image to it, or calibrate at "
                "the image's size."
            )
        if not np.any(np.isfinite(batch.ranges[scan_index])):
            console.print(
                f"[yellow]warning:[/yellow] scan {scan_index} of {escape(str(scan))} has no "
                "returns: only the image can show trunks.",
                soft_wrap=True,
            )
        rois = laser_rois(batch[scan_index])
        seg = segment_trunks(rgb, preset)
        if method == "xue2018":
            res = fuse_xue2018(rois, seg.regions, G, image_width=rgb.shape[1], bpa=bpa)
        else:
            if "camera" not in doc:
                raise ConfigError(
                    f"--method ours needs camera intrinsics in {calibration} "
                    "(run `stemmap calibrate` with --fx --cx --cy --width --height)."
                )
            cam = CameraModel(*doc["camera"])
            l2c = None
            if "laser_to_camera" in doc:
                l2c = RigidTransform(*doc["laser_to_camera"])
            res = fuse_ours(
                rois, seg.regions, G, rgb, cam, laser_to_camera=l2c, params=FusionParams(bpa=bpa)
            )
        with atomic_write(run.path(out_path)) as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(
                [
                    "kind",
                    "laser_index",
                    "region_index",
                    "x",
                    "y",
                    "width",
                    "mT",
                    "mNT",
                    "mTheta",
                    "conflict",
                    "is_trunk",
                ]
            )
            for k in range(len(res)):
                li, ri = int(res.laser_index[k]), int(res.region_index[k])
                kind = "pair" if li >= 0 and ri >= 0 else ("laser" if li >= 0 else "vision")
                x, y = res.centers[k]
                w.writerow(
                    [
                        kind,
                        li,
                        ri,
                        "" if math.isnan(x) else f"{x:.4f}",
                        "" if math.isnan(y) else f"{y:.4f}",
                        "" if math.isnan(res.diameters[k]) else f"{res.diameters[k]:.4f}",
                        f"{res.m_fused.t[k]:.4f}",
                        f"{res.m_fused.nt[k]:.4f}",
                        f"{res.m_fused.theta[k]:.4f}",
                        f"{res.conflict[k]:.4f}",
                        int(res.is_trunk[k]),
                    ]
                )
    console.print(
        f"{len(rois)} laser RoI(s), {len(seg.regions)} image region(s), "
        f"{len(res.association.pairs)} pair(s): {int(res.is_trunk.sum())} trunk(s) -> {out_path}"
    )


def register(app: typer.Typer) -> None:
    """Add calibrate, segment and fuse to the stemmap app."""
    app.command("calibrate")(calibrate)
    app.command("segment")(segment)
    app.command("fuse")(fuse)
