"""Trainable pixel classifier: training on synthetic photos, tree export, safe model files, CLI."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.errors import InputError
from stemmap.vision.segment_classifier import (
    TreeEnsemble,
    load_model,
    probability_map,
    save_model,
    segment_pixels,
    train_pixel_classifier,
)
from stemmap.vision.segment_features import feature_names, pixel_features

RUNNER = CliRunner()
W, H = 320, 240


def _scene(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A synthetic 'photo': dark mud with green foliage blobs and bright water patches, and 2-3
    pale leaning trunks with bark noise. Colour overlaps (brownish mud, pale water) make the
    texture and shape features matter."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(0, 1, (H, W, 3))
    img = np.empty((H, W, 3))
    img[:] = (60, 55, 40)
    img += 12 * cv2.GaussianBlur(noise, (0, 0), 1.0)
    yy, xx = np.mgrid[0:H, 0:W]
    for _ in range(12):  # foliage and water blobs
        cx, cy, r = rng.uniform(0, W), rng.uniform(0, H), rng.uniform(8, 30)
        blob = (xx - cx) ** 2 + (yy - cy) ** 2 < r * r
        img[blob] = (70, 140, 50) if rng.random() < 0.6 else (200, 205, 210)
        img[blob] += 25 * noise[blob]
    mask = np.zeros((H, W), bool)
    for _ in range(rng.integers(2, 4)):
        x0, lean, half = rng.uniform(30, W - 30), rng.uniform(-0.3, 0.3), rng.uniform(6, 16)
        centre = x0 + lean * (yy - H / 2)
        trunk = np.abs(xx - centre) < half
        bark = 18 * np.sin(yy[trunk] / rng.uniform(2, 4)) + 10 * noise[trunk][:, 0]
        img[trunk] = np.array([175, 150, 120]) + bark[:, None]
        mask |= trunk
    return np.clip(img, 0, 255).astype(np.uint8), mask


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(int((a | b).sum()), 1))


@pytest.fixture(scope="module")
def model():
    train = [_scene(s) for s in range(3)]
    return train_pixel_classifier(
        [t[0] for t in train], [t[1] for t in train], work_width=160, per_class=4000, max_iter=40
    )


def test_features_shape_and_finite() -> None:
    img, _ = _scene(0)
    f = pixel_features(img)
    assert f.shape == (H, W, len(feature_names())) and f.dtype == np.float32
    assert np.all(np.isfinite(f))


def test_trained_on_synthetic_segments_unseen_scenes(model) -> None:
    # held-out scenes (other seeds): the classifier learns bark vs mud / foliage / water.
    # 0.7: the masks are upsampled from 160 px, so the 6-16 px wide trunk edges cost ~10 %.
    for seed in (10, 11):
        img, gt = _scene(seed)
        seg = segment_pixels(img, model)
        assert seg.mask.shape == gt.shape
        assert _iou(seg.mask, gt) > 0.7, seed
        assert len(seg.regions) >= 1 and np.all(seg.regions.alpha > 0)


def test_exported_trees_equal_sklearn() -> None:
    from sklearn.ensemble import HistGradientBoostingClassifier
    from threadpoolctl import threadpool_limits

    rng = np.random.default_rng(1)
    X = rng.normal(size=(3000, 6)).astype(np.float32)
    X[rng.random(X.shape) < 0.02] = np.nan  # the export keeps the missing-value branch
    y = (np.nan_to_num(X[:, 0]) * np.nan_to_num(X[:, 3]) > 0.2).astype(np.uint8)
    with threadpool_limits(1):
        clf = HistGradientBoostingClassifier(max_iter=20, random_state=0).fit(X, y)
    t = TreeEnsemble.from_sklearn(clf)
    t.validate(6)
    np.testing.assert_allclose(t.raw_score(X), clf.decision_function(X), atol=1e-9)


def test_model_file_roundtrip_without_pickle(model, tmp_path: Path) -> None:
    f = tmp_path / "m.npz"
    save_model(model, f)
    with np.load(f, allow_pickle=False) as z:  # plain arrays only
        assert all(z[k].dtype != object for k in z.files)
    back = load_model(f)
    img, _ = _scene(20)
    np.testing.assert_array_equal(probability_map(img, back), probability_map(img, model))
    assert back.threshold == model.threshold and back.work_width == 160


def _rewrite(src: Path, dst: Path, **changes: object) -> None:
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    header = json.loads(bytes(arrays["header"]).decode())
    for k, v in changes.items():
        if k in header:
            header[k] = v
        else:
            arrays[k] = np.asarray(v, dtype=arrays[k].dtype)
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    np.savez(dst, **arrays)


def test_bad_model_files_are_clear_errors(model, tmp_path: Path) -> None:
    good = tmp_path / "good.npz"
    save_model(model, good)
    bad = tmp_path / "bad.npz"
    _rewrite(good, bad, format_version=99)
    with pytest.raises(InputError, match="format version 99"):
        load_model(bad)
    _rewrite(good, bad, feature_version=0)
    with pytest.raises(InputError, match="feature set"):
        load_model(bad)
    with np.load(good) as z:
        left = z["left"].copy()
        leaf = z["is_leaf"]
    left[np.flatnonzero(leaf == 0)[0]] = 0  # a split pointing back to the root: a cycle
    _rewrite(good, bad, left=left)
    with pytest.raises(InputError, match="invalid child"):
        load_model(bad)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a readable"):
        load_model(tmp_path / "junk.npz")
    (tmp_path / "cut.npz").write_bytes(good.read_bytes()[:2000])  # a truncated download
    with pytest.raises(InputError, match="not a readable"):
        load_model(tmp_path / "cut.npz")
    np.save(tmp_path / "one.npy", np.zeros(3))
    with pytest.raises(InputError, match="single"):
        load_model(tmp_path / "one.npy")
    with pytest.raises(InputError, match="does not exist"):
        load_model(tmp_path / "missing.npz")
    _rewrite(good, bad, colour_norm="retinex")
    with pytest.raises(InputError, match="colour_norm"):
        load_model(bad)
    _rewrite(good, bad, format_version=1)  # v1 had no colour normalisation field
    with pytest.raises(InputError, match="version 1 model cannot carry colour_norm"):
        load_model(bad)


def test_version_1_files_read_as_without_colour_norm(model, tmp_path: Path) -> None:
    """Files written before format v2 (no ``colour_norm`` in the header) still load, as
    ``colour_norm="none"``; a grey-world model round-trips and predicts differently from the
    same trees on raw colours."""
    good, old = tmp_path / "good.npz", tmp_path / "v1.npz"
    save_model(model, good)
    with np.load(good, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    header = json.loads(bytes(arrays["header"]).decode())
    header["format_version"] = 1
    del header["colour_norm"]
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    np.savez(old, **arrays)
    assert load_model(old).colour_norm == "none"
    gw = replace(model, colour_norm="grey_world")
    raw = replace(model, colour_norm="none")
    save_model(gw, good)
    back = load_model(good)
    assert back.colour_norm == "grey_world"
    img, _ = _scene(21)
    img = (img * np.array([1.0, 0.8, 0.6])).astype(np.uint8)  # a colour cast
    np.testing.assert_array_equal(probability_map(img, back), probability_map(img, gw))
    assert not np.array_equal(probability_map(img, gw), probability_map(img, raw))


def test_cli_train_png_and_yolo_labels_then_segment_with_overlay(tmp_path: Path) -> None:
    photos, labels = tmp_path / "photos", tmp_path / "labels"
    photos.mkdir()
    labels.mkdir()
    for s in range(3):
        img, mask = _scene(s)
        cv2.imwrite(str(photos / f"p{s}.png"), img[..., ::-1])
        if s < 2:
            cv2.imwrite(str(labels / f"p{s}.png"), mask.astype(np.uint8) * 255)
        else:  # YOLO polygons: the outline of each trunk, normalised
            cs, _ = cv2.findContours(
                mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE
            )
            lines = [
                "0 " + " ".join(f"{x / W:.5f} {y / H:.5f}" for x, y in c.reshape(-1, 2)) for c in cs
            ]
            (labels / f"p{s}.txt").write_text("\n".join(lines) + "\n")
    mfile = tmp_path / "trunks.npz"
    res = RUNNER.invoke(
        app,
        ["segment", "--train", str(photos), "--labels", str(labels), "--model-out", str(mfile),
         "--work-width", "160"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert load_model(mfile).meta["trained_on"] == ["p0.png", "p1.png", "p2.png"]
    img, gt = _scene(12)
    photo = tmp_path / "test.png"
    cv2.imwrite(str(photo), img[..., ::-1])
    mask_f, ov_f = tmp_path / "mask.png", tmp_path / "overlay.png"
    res = RUNNER.invoke(
        app,
        ["segment", str(photo), "--model", str(mfile), "--out", str(mask_f),
         "--overlay", str(ov_f)],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    m = cv2.imread(str(mask_f), cv2.IMREAD_GRAYSCALE) > 0
    assert _iou(m, gt) > 0.7
    ov = cv2.imread(str(ov_f))
    assert ov.shape == (H, W, 3)
    changed = np.any(ov != img[..., ::-1], axis=2)
    assert changed[m].mean() > 0.95 and changed[~m].mean() < 0.1  # drawn over the mask only
    # missing label for a training image -> a clear error naming the file
    (photos / "p9.png").write_bytes(photo.read_bytes())
    res = RUNNER.invoke(
        app, ["segment", "--train", str(photos), "--labels", str(labels), "--model-out", str(mfile)]
    )
    assert res.exit_code == 2 and "no label file named p9" in " ".join(res.output.split())


def test_cli_method_and_model_errors(tmp_path: Path) -> None:
    img, _ = _scene(3)
    photo = tmp_path / "a.png"
    cv2.imwrite(str(photo), img)
    out = tmp_path / "m.png"
    res = RUNNER.invoke(app, ["segment", str(photo), "--out", str(out), "--method", "nope"])
    assert res.exit_code == 2 and "--method must be one of" in " ".join(res.output.split())
    res = RUNNER.invoke(app, ["segment", str(photo), "--out", str(out), "--model", str(photo)])
    assert res.exit_code == 2 and "not a readable .npz" in " ".join(res.output.split())
    res = RUNNER.invoke(  # the model file would overwrite a training image: refused
        app, ["segment", "--train", str(photo), "--labels", str(out), "--model-out", str(photo)]
    )
    assert res.exit_code != 0 and str(photo) in " ".join(res.output.split())
    assert cv2.imread(str(photo)) is not None
    res = RUNNER.invoke(app, ["segment", str(photo), "--out", str(out)])  # shipped model
    assert res.exit_code == 0 and "(pixel)" in res.output
    assert cv2.imread(str(out), cv2.IMREAD_GRAYSCALE).shape == (H, W)
    res = RUNNER.invoke(app, ["segment", "--help"])
    assert "CROPS THE TOP 25 %" in " ".join(res.output.replace("│", " ").split())  # box wrap
