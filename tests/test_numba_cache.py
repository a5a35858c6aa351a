"""numba's cache of a module that compiles in another module's kernels is dropped when that
other module changes (stemmap._numba_cache)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

from stemmap import _numba_cache
from stemmap._numba_cache import drop_stale_cache


def _fake(tmp_path: Path) -> tuple[SimpleNamespace, Path, Path, Path]:
    mod = tmp_path / "kern.py"
    dep = tmp_path / "dep.py"
    mod.write_text("# kernels\n")
    dep.write_text("X = 1\n")
    cache = tmp_path / "cache"
    cache.mkdir()
    return SimpleNamespace(_cache=SimpleNamespace(_cache_path=str(cache))), mod, dep, cache


def _entries(cache: Path) -> list[str]:
    for name in ("kern.f-3.py311.nbi", "kern.f-3.py311.1.nbc"):
        (cache / name).write_bytes(b"x")
    (cache / "other.g-1.py311.nbi").write_bytes(b"x")  # another module's entry: never touched
    return sorted(p.name for p in cache.iterdir() if p.name.startswith("kern.f"))


def test_cache_dropped_only_when_a_dependency_changes(tmp_path: Path) -> None:
    disp, mod, dep, cache = _fake(tmp_path)
    _entries(cache)
    # no record yet: whatever is cached may predate the dependency -> dropped
    assert drop_stale_cache(disp, str(mod), str(dep))
    assert not list(cache.glob("kern.*.nb?"))
    assert (cache / "other.g-1.py311.nbi").exists()
    # the kernels recompile and cache again; the dependency is unchanged -> kept
    kept = _entries(cache)
    assert not drop_stale_cache(disp, str(mod), str(dep))
    assert sorted(p.name for p in cache.glob("kern.*.nb?")) == kept
    # an edit of the dependency (content, not mtime, is what counts) -> dropped
    dep.write_text("X = 2\n")
    assert drop_stale_cache(disp, str(mod), str(dep))
    assert not list(cache.glob("kern.*.nb?"))


def test_an_edit_of_the_compile_flags_alone_drops_the_cache(tmp_path: Path, monkeypatch) -> None:
    """numba's cache key holds no compile option (``_nrt`` of stemmap._leaf_jit): a change of
    the flag module drops every caller's entries, with or without listed dependencies."""
    disp, mod, dep, cache = _fake(tmp_path)
    flags = tmp_path / "_leaf_jit.py"
    flags.write_text("NRT = False\n")
    monkeypatch.setattr(_numba_cache, "FLAGS_FILE", flags)
    for deps in ((str(dep),), ()):
        drop_stale_cache(disp, str(mod), *deps)  # first record
        kept = _entries(cache)
        assert not drop_stale_cache(disp, str(mod), *deps)
        assert sorted(p.name for p in cache.glob("kern.*.nb?")) == kept
        flags.write_text(flags.read_text() + "# edited\n")  # the dependency itself unchanged
        assert drop_stale_cache(disp, str(mod), *deps)
        assert not list(cache.glob("kern.*.nb?"))


def test_the_flags_file_is_the_leaf_jit_module() -> None:
    from stemmap import _leaf_jit

    assert Path(_leaf_jit.__file__).resolve() == _numba_cache.FLAGS_FILE.resolve()


def test_unwritable_cache_is_not_an_error(tmp_path: Path) -> None:
    disp, mod, dep, _ = _fake(tmp_path)
    blocker = tmp_path / "file"
    blocker.write_text("")
    disp._cache._cache_path = str(blocker / "sub")  # cannot be created: a file is in the way
    assert drop_stale_cache(disp, str(mod), str(dep))


def test_fallback_without_numba_internals(tmp_path: Path) -> None:
    _, mod, _, _ = _fake(tmp_path)
    assert _numba_cache._cache_dir(object(), mod) == tmp_path / "__pycache__"


def test_the_detector_kernel_records_its_dependencies() -> None:
    """The real module: numba's cache location is found and the record matches the files the
    kernel compiles in (so a later edit of either is noticed): every stemmap module
    _detect_fast imports kernels or constants from, and theirs in turn."""
    from stemmap.scan import (
        _corners,
        _detect_fast,
        _fast_arcs,
        _fast_candidates,
        _fast_robust,
        _fast_segments,
        _fast_step_split,
        _fit_geometric,
        _fit_lm,
        _gaps,
        _kernel_params,
        features,
    )

    cache = _numba_cache._cache_dir(_detect_fast._detect_kernel, Path(_detect_fast.__file__))
    record = cache / "_detect_fast.deps-sha256"
    if not record.exists():  # a read-only install: nothing to check
        return
    assert not drop_stale_cache(
        _detect_fast._detect_kernel,
        _detect_fast.__file__,
        _fit_geometric.__file__,
        features.__file__,
        _corners.__file__,
        _fast_arcs.__file__,
        _fast_candidates.__file__,
        _gaps.__file__,
        _fast_robust.__file__,
        _fast_segments.__file__,
        _fast_step_split.__file__,
        _fit_lm.__file__,
        _kernel_params.__file__,
    )


def test_the_modules_the_detector_kernel_calls_record_theirs() -> None:
    """The fit's kernels compile in its Levenberg-Marquardt core (_fit_lm), the gap cuts the
    corners' sagitta, the per-candidate steps the fit and the cuts; the leaf modules (_fit_lm,
    _corners, _fast_robust, _fast_segments) compile in nothing but the flags: each module's
    record matches those files (and the flag module, always hashed)."""
    from stemmap.scan import (
        _corners,
        _fast_arcs,
        _fast_candidates,
        _fast_robust,
        _fast_segments,
        _fast_step_split,
        _fit_geometric,
        _fit_lm,
        _gaps,
        _kernel_params,
        features,
    )

    candidate_deps = (
        _fit_geometric.__file__,
        features.__file__,
        _corners.__file__,
        _fast_robust.__file__,
        _fast_segments.__file__,
        _fit_lm.__file__,
        _kernel_params.__file__,
    )
    for mod, disp, deps in (
        (_fit_lm, _fit_lm.levenberg_marquardt, ()),
        (_corners, _corners.sagitta, ()),
        (_fast_robust, _fast_robust._range_roughness, ()),
        (_fast_segments, _fast_segments._pairwise, ()),
        (_fit_geometric, _fit_geometric._fit_segments, (_fit_lm.__file__,)),
        (_gaps, _gaps.gap_cut_flags, (_corners.__file__,)),
        (_fast_candidates, _fast_candidates._fit_candidate, candidate_deps),
        (_fast_arcs, _fast_arcs.arc_candidate, (_fast_candidates.__file__, *candidate_deps)),
        (
            _fast_step_split,
            _fast_step_split.step_emit,
            (_fast_arcs.__file__, _fast_candidates.__file__, *candidate_deps),
        ),
    ):
        cache = _numba_cache._cache_dir(disp, Path(mod.__file__))
        if not (cache / f"{Path(mod.__file__).stem}.deps-sha256").exists():
            continue  # a read-only install
        assert not drop_stale_cache(disp, mod.__file__, *deps)


def test_the_dependency_lists_cover_every_imported_kernel_module() -> None:
    """Every stemmap.scan module whose names _detect_fast, _fast_candidates, _fast_arcs,
    _fast_step_split, _fit_geometric or _gaps import is in that module's drop_stale_cache call
    (read from the source, so a new split is not missed)."""
    import ast

    from stemmap.scan import (
        _detect_fast,
        _fast_arcs,
        _fast_candidates,
        _fast_step_split,
        _fit_geometric,
        _gaps,
    )

    kernels = (_detect_fast, _fast_arcs, _fast_candidates, _fast_step_split, _fit_geometric, _gaps)
    for mod in kernels:
        tree = ast.parse(Path(mod.__file__).read_text())
        imported: set[str] = set()
        for node in tree.body:
            if isinstance(node, ast.ImportFrom) and node.module:
                if node.module == "stemmap.scan":
                    imported |= {a.name for a in node.names}
                elif node.module.startswith("stemmap.scan."):
                    imported.add(node.module.rsplit(".", 1)[1])
        listed: set[str] = set()
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr == "drop_stale_cache"
            ):
                for arg in node.args[2:]:
                    if isinstance(arg, ast.Attribute) and isinstance(arg.value, ast.Name):
                        listed.add(arg.value.id)
        assert imported <= listed, (mod.__name__, imported - listed)


def _module_calls_drop_stale_cache(tree: object) -> bool:
    import ast

    assert isinstance(tree, ast.Module)
    return any(
        isinstance(node, ast.Expr)
        and isinstance(node.value, ast.Call)
        and isinstance(node.value.func, ast.Attribute)
        and node.value.func.attr == "drop_stale_cache"
        for node in tree.body
    )


def test_every_module_compiled_with_the_leaf_flags_checks_its_cache() -> None:
    """numba's cache key ignores the ``_nrt`` flag of stemmap._leaf_jit, so every stemmap
    module whose cached kernels are compiled with it -- it imports ``leaf_njit`` / ``nrt_njit``,
    or imports kernels from a module that does -- calls drop_stale_cache at import (at module
    level, so the call runs before any kernel loads its cache), which hashes the flag module."""
    import ast

    import stemmap

    root = Path(stemmap.__file__).parent
    trees = {}
    for path in sorted(root.rglob("*.py")):
        name = ".".join(path.relative_to(root.parent).with_suffix("").parts)
        trees[name] = ast.parse(path.read_text())

    def imported_modules(name: str, tree: ast.Module) -> set[str]:
        mods: set[str] = set()
        for node in tree.body:
            if isinstance(node, ast.ImportFrom) and node.module:
                mods.add(node.module)
                mods |= {f"{node.module}.{a.name}" for a in node.names}  # submodules
        return mods & set(trees)

    leaf = {n for n, t in trees.items() if "stemmap._leaf_jit" in imported_modules(n, t)}
    assert {"stemmap.scan._fit_lm", "stemmap.scan._corners"} <= leaf  # the scan is real
    using = set(leaf)
    for name, tree in trees.items():
        cached = "cache=True" in ast.unparse(tree)
        if cached and imported_modules(name, tree) & leaf:
            using.add(name)
    missing = sorted(n for n in using if not _module_calls_drop_stale_cache(trees[n]))
    assert not missing, missing
