"""stemmap.io.products: staged, all-or-nothing run products with a run.json manifest."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from stemmap.io.products import OutputError, run_products, verify_run


def _visible(d: Path) -> dict[str, str]:
    return {p.name: p.read_text() for p in sorted(d.iterdir()) if not p.name.startswith(".")}


def _folder_run(out: Path, tag: str, names=("a.csv", "b.csv", "c.png")) -> None:
    with run_products("test", out_dir=out) as run:
        for n in names:
            (run.dir / n).write_text(f"{tag} {n}\n")


def test_folder_run_switches_the_whole_set(tmp_path):
    out = tmp_path / "res"
    _folder_run(out, "old", ("a.csv", "b.csv", "stale.txt"))
    assert verify_run(out / "run.json") == []
    _folder_run(out, "new")
    # the new set replaced the old one as a whole: the old run's stale.txt is gone
    assert set(_visible(out)) == {"a.csv", "b.csv", "c.png", "run.json"}
    assert all(v.startswith("new") for k, v in _visible(out).items() if k != "run.json")
    doc = json.loads((out / "run.json").read_text())
    assert doc["mode"] == "folder-switch" and doc["status"] == "complete"
    assert [o["path"] for o in doc["outputs"]] == ["a.csv", "b.csv", "c.png"]
    assert verify_run(out / "run.json") == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]  # no staging left


def test_failed_folder_run_keeps_the_previous_set(tmp_path):
    out = tmp_path / "res"
    _folder_run(out, "old")
    before = _visible(out)

    def failing_run() -> None:
        with run_products("test", out_dir=out) as run:
            (run.dir / "a.csv").write_text("new a\n")
            raise RuntimeError("injected failure after one product")

    with pytest.raises(RuntimeError):
        failing_run()
    assert _visible(out) == before and verify_run(out / "run.json") == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]


_KILLED = textwrap.dedent(
    """
    import os, signal, sys
    from pathlib import Path
    from stemmap.io.products import run_products
    out, mode = Path(sys.argv[1]), sys.argv[2]
    if mode == "folder":
        with run_products("kill", out_dir=out) as run:
            (run.dir / "a.csv").write_text("new a\\n")
            (run.dir / "b.csv").write_text("new b (half")
            os.kill(os.getpid(), signal.SIGKILL)
    else:
        a, b = out / "a.csv", out / "b.csv"
        with run_products("kill", outputs=[a, b]) as run:
            run.path(a).write_text("new a\\n")
            run.path(b).write_text("new b (half")
            os.kill(os.getpid(), signal.SIGKILL)
    """
)


@pytest.mark.parametrize("mode", ["folder", "files"])
def test_sigkill_mid_write_leaves_the_previous_complete_set(tmp_path, mode):
    out = tmp_path / "res"
    if mode == "folder":
        _folder_run(out, "old", ("a.csv", "b.csv"))
        manifest = out / "run.json"
    else:
        out.mkdir()
        with run_products("test", outputs=[out / "a.csv", out / "b.csv"]) as run:
            run.path(out / "a.csv").write_text("old a.csv\n")
            run.path(out / "b.csv").write_text("old b.csv\n")
        manifest = out / "a.csv.run.json"
    before = _visible(out)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2] / "src"))
    p = subprocess.run([sys.executable, "-c", _KILLED, str(out), mode], env=env, check=False)
    assert p.returncode == -signal.SIGKILL
    assert _visible(out) == before  # the previous complete set, byte for byte
    assert verify_run(manifest) == []
    # the killed run's staging is hidden; the next run cleans nothing it does not own
    if mode == "folder":
        _folder_run(out, "next", ("a.csv",))
        assert _visible(out) == {"a.csv": "next a.csv\n", "run.json": _visible(out)["run.json"]}


def test_file_commit_interrupted_is_flagged(tmp_path, monkeypatch):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    with run_products("test", outputs=[a, b]) as run:
        run.path(a).write_text("old a\n")
        run.path(b).write_text("old b\n")
    import stemmap.io.products as products

    real = os.replace
    calls = {"n": 0}

    def flaky(src, dst):
        if Path(dst).name == "b.csv":
            calls["n"] += 1
            raise OSError(5, "Input/output error", str(src))
        return real(src, dst)

    monkeypatch.setattr(products.os, "replace", flaky)

    def second_run() -> None:
        with run_products("test", outputs=[a, b]) as run:
            run.path(a).write_text("new a\n")
            run.path(b).write_text("new b\n")

    with pytest.raises(OutputError, match=r"b\.csv"):
        second_run()
    monkeypatch.setattr(products.os, "replace", real)
    assert calls["n"] == 1
    problems = verify_run(tmp_path / "a.csv.run.json")
    assert "committing" in problems[0] and any("b.csv" in p for p in problems)


def test_folder_with_foreign_files_is_updated_per_file(tmp_path):
    out = tmp_path / "res"
    out.mkdir()
    (out / "notes.txt").write_text("the user's own file")
    _folder_run(out, "new", ("a.csv",))
    assert _visible(out)["notes.txt"] == "the user's own file"
    assert _visible(out)["a.csv"] == "new a.csv\n"
    doc = json.loads((out / "run.json").read_text())
    assert doc["mode"] == "per-file" and [o["path"] for o in doc["outputs"]] == ["a.csv"]
    assert verify_run(out / "run.json") == []


def test_input_hashes_and_folder_inputs(tmp_path):
    import hashlib

    d = tmp_path / "bag"
    d.mkdir()
    (d / "x.db3").write_bytes(b"12345")
    f = tmp_path / "in.csv"
    f.write_bytes(b"abc")
    out = tmp_path / "o.csv"
    with run_products("test", inputs=[f, d], outputs=[out]) as run:
        run.path(out).write_text("x")
        # a file of an input folder is an input too
        with pytest.raises(OutputError, match="input folder"):
            run.path(d / "x.db3")
    doc = json.loads((tmp_path / "o.csv.run.json").read_text())
    assert doc["inputs"][0]["sha256"] == hashlib.sha256(b"abc").hexdigest()
    assert doc["inputs"][1]["kind"] == "folder" and doc["inputs"][1]["files"] == 1


def test_file_sha256_reads_an_unchanged_file_once(tmp_path, monkeypatch) -> None:
    """Both manifests of a run and the tile engine record the same hash: one read per file;
    a rewritten file (new mtime/size) is hashed again."""
    import hashlib
    import os

    from stemmap.io import products

    f = tmp_path / "a.bin"
    f.write_bytes(b"x" * 1000)
    calls = []
    real_open = open
    monkeypatch.setattr(
        "builtins.open", lambda p, *a, **k: (calls.append(p), real_open(p, *a, **k))[1]
    )
    first = products.file_sha256(f)
    assert products.file_sha256(f) == first == hashlib.sha256(b"x" * 1000).hexdigest()
    assert len(calls) == 1
    f.write_bytes(b"y" * 1001)
    os.utime(f, ns=(1, 2))
    assert products.file_sha256(f) == hashlib.sha256(b"y" * 1001).hexdigest()
    assert len(calls) == 2


def test_a_new_output_folder_gets_the_umask_permissions(tmp_path):
    # the user audit (docs/cli.md): `map --out NEW` left a 0700 folder (mkdtemp's mode), so
    # nobody but its owner could read the products
    old = os.umask(0o022)
    try:
        _folder_run(tmp_path / "res", "new")
    finally:
        os.umask(old)
    assert (tmp_path / "res").stat().st_mode & 0o777 == 0o755


def test_two_outputs_resolving_to_one_file_are_refused(tmp_path):
    a = tmp_path / "a.csv"
    (tmp_path / "link.csv").symlink_to(a)
    for outs in ([a, a], [a, tmp_path / "link.csv"], [a, tmp_path / "a.csv.run.json"]):
        with pytest.raises(OutputError), run_products("t", outputs=outs) as run:
            run.path(outs[0]).write_text("x")
        assert not a.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.csv"]  # no staging left


def _folder_product(run, final: Path, payload: str) -> None:
    """What ``io convert-scans --out NAME`` does: a file output whose product is a folder."""
    staged = run.path(final)
    staged.mkdir()
    (staged / "metadata.yaml").write_text(payload)


def test_folder_product_never_replaces_a_folder_of_other_files(tmp_path):
    # the user walk (Dec 4): `io convert-scans scans.npz --out myfolder` (a ROS 2 bag folder)
    # replaced an existing folder of the user's as a whole: its files were deleted
    mine = tmp_path / "myfolder"
    mine.mkdir()
    (mine / "notes.txt").write_text("precious")
    with (
        pytest.raises(OutputError, match="folder holding files this command did not write"),
        run_products("io convert-scans", outputs=[mine]) as run,
    ):
        _folder_product(run, mine, "new")
    assert (mine / "notes.txt").read_text() == "precious"
    assert not list(tmp_path.glob(".stemmap-stage-*"))


def test_folder_product_replaces_its_own_earlier_output(tmp_path):
    out = tmp_path / "bag"
    out.mkdir()  # an empty folder is fine
    for payload in ("first", "second"):
        with run_products("io convert-scans", outputs=[out]) as run:
            _folder_product(run, out, payload)
        assert (out / "metadata.yaml").read_text() == payload
    (out / "extra.txt").write_text("added by hand")  # no longer what the run wrote
    with (
        pytest.raises(OutputError, match="did not write"),
        run_products("io convert-scans", outputs=[out]) as run,
    ):
        _folder_product(run, out, "third")
    assert (out / "extra.txt").is_file() and (out / "metadata.yaml").read_text() == "second"
