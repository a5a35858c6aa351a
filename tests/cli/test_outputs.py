"""Output safety (issue 13): no command overwrites an input; OS errors are one clean line."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app

runner = CliRunner()

#: every writing command: (argv builder, input file names it reads). ``{in}`` is the input the
#: output is aimed at; the other inputs are dummies (the refusal happens before any reading).
COMMANDS: dict[str, tuple[list[str], list[str]]] = {
    "detect": (["detect", "{in0}", "--out", "{out}"], ["scans.npz"]),
    "stems": (["stems", "{in0}", "--out", "{out}"], ["cloud.xyz"]),
    "stems-png": (["stems", "{in0}", "--out", "s.csv", "--png", "{out}"], ["cloud.xyz"]),
    "convert-scans": (["io", "convert-scans", "{in0}", "--out", "{out}"], ["scans.csv"]),
    "calibrate": (["calibrate", "{in0}", "--out", "{out}"], ["pairs.csv"]),
    "segment": (["segment", "{in0}", "--out", "{out}"], ["frame.png"]),
    "segment-rois": (["segment", "{in0}", "--out", "m.png", "--rois", "{out}"], ["frame.png"]),
    "fuse": (
        ["fuse", "--scan", "{in0}", "--image", "{in1}", "--calibration", "{in2}", "--out", "{out}"],
        ["scan.npz", "frame.png", "calib.json"],
    ),
    "sim-score": (
        ["sim", "score", "{in0}", "--run", "{in1}", "--json", "{out}"],
        ["stems.csv", "run.npz"],
    ),
}


def _argv(tmpl: list[str], names: list[str], tmp: Path, out: Path) -> list[str]:
    sub = {f"{{in{k}}}": str(tmp / n) for k, n in enumerate(names)}
    sub["{out}"] = str(out)
    return [sub.get(a, a) for a in tmpl]


def _inputs(tmp: Path, names: list[str]) -> dict[Path, bytes]:
    content = {}
    for k, n in enumerate(names):
        p = tmp / n
        p.write_bytes(f"input {k} of the test, must survive\n".encode())
        content[p] = p.read_bytes()
    return content


def _option(tmpl: list[str]) -> str:
    """The option whose value is the output under test (``--out``, ``--png``, ``--json``...)."""
    return tmpl[tmpl.index("{out}") - 1]


def _one_error_line(res) -> str:
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    errs = [ln for ln in lines if ln.startswith("error:")]
    assert len(errs) == 1, res.output
    assert "Traceback" not in res.output
    return errs[0]


@pytest.mark.parametrize("how", ["same", "symlink", "hardlink", "relative"])
@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_output_that_is_an_input_is_refused(tmp_path, monkeypatch, name, how):
    tmpl, names = COMMANDS[name]
    content = _inputs(tmp_path, names)
    target = tmp_path / names[0]
    if how == "same":
        out = target
    elif how == "symlink":
        out = tmp_path / "link"
        out.symlink_to(target)
    elif how == "hardlink":
        out = tmp_path / "hard"
        os.link(target, out)
    else:
        (tmp_path / "sub").mkdir()
        monkeypatch.chdir(tmp_path / "sub")
        out = Path("..") / names[0]
    res = runner.invoke(app, _argv(tmpl, names, tmp_path, out))
    assert res.exit_code == 2, res.output
    line = _one_error_line(res)
    assert "refusing to overwrite an input" in line and names[0] in line
    # the message starts with the option that gave the output path (not always "--out")
    assert line.startswith(f"error: {_option(tmpl)} {str(out)!r} is the same file as the input ")
    for p, b in content.items():
        assert p.read_bytes() == b
    assert not list(tmp_path.glob(".stemmap-stage-*"))


def test_map_out_folder_containing_the_input_is_refused(tmp_path):
    bag = tmp_path / "run.bag"
    bag.write_bytes(b"not really a bag")
    res = runner.invoke(app, ["map", str(bag), "--out", str(tmp_path)])
    assert res.exit_code == 2
    assert "contains the input" in _one_error_line(res)
    res = runner.invoke(app, ["map", str(bag), "--out", str(bag)])
    assert res.exit_code == 2 and "refusing to overwrite an input" in _one_error_line(res)
    assert bag.read_bytes() == b"not really a bag"


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_file_where_a_folder_should_be(tmp_path, name):
    tmpl, names = COMMANDS[name]
    _inputs(tmp_path, names)
    (tmp_path / "blocker").write_text("a file")
    out = tmp_path / "blocker" / "deeper" / "out.csv"
    res = runner.invoke(app, _argv(tmpl, names, tmp_path, out))
    assert res.exit_code == 2, res.output
    line = _one_error_line(res)
    assert "blocker" in line and "file where a folder should be" in line
    assert f"cannot write {_option(tmpl)} {str(out)!r}:" in line


@pytest.mark.parametrize("name", ["detect", "calibrate", "segment", "fuse", "stems"])
def test_existing_folder_given_as_a_file(tmp_path, name):
    tmpl, names = COMMANDS[name]
    _inputs(tmp_path, names)
    out = tmp_path / "already.csv"
    out.mkdir()
    res = runner.invoke(app, _argv(tmpl, names, tmp_path, out))
    assert res.exit_code == 2
    assert "it is a folder" in _one_error_line(res)
    assert out.is_dir()


@pytest.mark.parametrize(
    "argv", [["demo", "--out", "{f}"], ["map", "--sim", "--out", "{f}"]], ids=["demo", "map"]
)
def test_folder_commands_refuse_a_file_as_out(tmp_path, argv):
    f = tmp_path / "a_file"
    f.write_text("keep me")
    res = runner.invoke(app, [a.replace("{f}", str(f)) for a in argv])
    assert res.exit_code == 2
    assert "is a file, but must be a folder" in _one_error_line(res)
    assert f.read_text() == "keep me"


def test_harvest_png_blocked(tmp_path):
    (tmp_path / "blocker").write_text("x")
    res = runner.invoke(app, ["harvest-sim", "--png", str(tmp_path / "blocker" / "h.png")])
    assert res.exit_code == 2 and "blocker" in _one_error_line(res)


def _scans(tmp_path: Path) -> Path:
    from stemmap.io.scans import write_scans_npz
    from stemmap.types import ScanBatch

    p = tmp_path / "scans.npz"
    a = np.linspace(-1.5, 1.5, 181)
    r = np.full((3, a.size), 8.0)
    r[:, 85:95] = 3.0 - 0.15 * np.cos(a[85:95] * 0)  # a wall-like blob; content is irrelevant
    write_scans_npz(p, ScanBatch(r, np.arange(3) * 0.1, float(a[0]), float(a[1] - a[0])))
    return p


@pytest.mark.parametrize(
    "err",
    [errno.EROFS, errno.EACCES, errno.ENOSPC],
    ids=["read-only", "no-permission", "disk-full"],
)
def test_os_errors_while_writing_are_one_line(tmp_path, monkeypatch, err):
    """Root ignores chmod: the OS refusal is injected at the write of the staged product."""
    import stemmap.io.atomic as atomic

    src = _scans(tmp_path)
    out = tmp_path / "prev.csv"
    out.write_text("previous complete product\n")
    real = atomic.os.fsync

    def failing(fd):
        raise OSError(err, os.strerror(err))

    monkeypatch.setattr(atomic.os, "fsync", failing)
    res = runner.invoke(app, ["detect", str(src), "--out", str(out)])
    monkeypatch.setattr(atomic.os, "fsync", real)
    assert res.exit_code == 2
    line = _one_error_line(res)
    assert str(out) in line and os.strerror(err) in line
    assert out.read_text() == "previous complete product\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["prev.csv", "scans.npz"]


def test_os_error_creating_the_staging_folder(tmp_path, monkeypatch):
    import stemmap.io.products as products

    def refuse(*a, **k):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), k.get("dir"))

    monkeypatch.setattr(products.tempfile, "mkdtemp", refuse)
    src = _scans(tmp_path)
    res = runner.invoke(app, ["detect", str(src), "--out", str(tmp_path / "o.csv")])
    assert res.exit_code == 2
    line = _one_error_line(res)
    assert "o.csv" in line and "read-only" in line


def test_long_error_line_is_not_wrapped(tmp_path):
    deep = tmp_path / ("x" * 120) / "missing.npz"
    res = runner.invoke(app, ["detect", str(deep), "--out", str(tmp_path / "o.csv")])
    assert res.exit_code == 2
    assert str(deep) in _one_error_line(res)


def test_detect_writes_a_manifest(tmp_path):
    import json

    from stemmap.io.products import file_sha256, verify_run

    src = _scans(tmp_path)
    out = tmp_path / "o.csv"
    res = runner.invoke(app, ["detect", str(src), "--out", str(out), "-q"])
    assert res.exit_code == 0, res.output
    m = tmp_path / "o.csv.run.json"
    doc = json.loads(m.read_text())
    assert doc["status"] == "complete" and doc["command"] == "detect"
    assert doc["inputs"][0]["sha256"] == file_sha256(src)
    assert doc["inputs"][0]["size"] == src.stat().st_size
    assert doc["outputs"] == [
        {"path": "o.csv", "kind": "file", "size": out.stat().st_size, "sha256": file_sha256(out)}
    ]
    assert doc["parameters"]["preset"] == "stemmap" and "numpy" in doc["libraries"]
    assert doc["started_utc"] <= doc["finished_utc"]
    assert verify_run(m) == []
    out.write_text("edited")
    assert "differs" in verify_run(m)[0]


@pytest.mark.parametrize(
    ("argv", "inputs"),
    [
        (["detect", "{in0}", "--out", "{out}", "--rejected", "{out}"], ["scans.npz"]),
        (["stems", "{in0}", "--out", "{out}", "--profile", "{out}"], ["cloud.xyz"]),
        (["segment", "{in0}", "--out", "{out}", "--overlay", "{out}"], ["frame.png"]),
    ],
)
def test_two_outputs_on_one_file_are_refused(tmp_path, argv, inputs):
    # the user audit (docs/cli.md): the second product silently replaced the first and the
    # command reported both as written
    _inputs(tmp_path, inputs)
    out = tmp_path / "o.csv"
    res = runner.invoke(app, _argv(argv, inputs, tmp_path, out))
    assert res.exit_code == 2, res.output
    assert "given twice" in _one_error_line(res)
    assert not out.exists()


def test_an_output_on_the_manifest_is_refused(tmp_path):
    src = _scans(tmp_path)
    out, manifest = tmp_path / "o.csv", tmp_path / "o.csv.run.json"
    res = runner.invoke(app, ["detect", str(src), "--out", str(out), "--rejected", str(manifest)])
    assert res.exit_code == 2, res.output
    assert "manifest" in _one_error_line(res)
    assert not out.exists() and not manifest.exists()


_SIGTERMED = """
import sys, time
import stemmap.scan.detect as detect

def stalled(self, *args, **kwargs):
    print("detecting", flush=True)
    time.sleep(120)

detect.ScanTrunkDetector.detect_batch = stalled
sys.argv = ["stemmap", "detect", sys.argv[1], "--out", sys.argv[2], "-q"]
from stemmap.cli import main
main()
"""


def _signalled(tmp_path: Path, sig: int) -> tuple[int, str]:
    """Run ``detect`` (stalled mid-run) in a subprocess, send it ``sig``: (exit code, stderr)."""
    from _signals import run_and_signal

    src = _scans(tmp_path)
    return run_and_signal(_SIGTERMED, [str(src), str(tmp_path / "o.csv")], sig, "detecting")


def test_sigterm_discards_the_staged_products(tmp_path):
    # the user audit (docs/cli.md): SIGTERM (timeout, a job scheduler, docker stop) killed the
    # run like SIGKILL and left its hidden staging folder behind; it now unwinds like Ctrl-C
    import signal

    code, err = _signalled(tmp_path, signal.SIGTERM)
    assert code == 128 + signal.SIGTERM, err
    assert "Traceback" not in err and "error: terminated (SIGTERM)" in err
    assert sorted(q.name for q in tmp_path.iterdir()) == ["scans.npz"]  # no product, no staging


def test_ctrl_c_says_the_products_were_dropped(tmp_path):
    # the user walk (Dec 4): Ctrl-C ended a run with exit code 130 and an empty line on
    # stderr, where SIGTERM says what happened to the products
    import signal

    code, err = _signalled(tmp_path, signal.SIGINT)
    assert code == 130, err
    assert "Traceback" not in err
    assert "error: interrupted (Ctrl-C); the products of this run were not written." in err
    assert sorted(q.name for q in tmp_path.iterdir()) == ["scans.npz"]  # no product, no staging
