"""Run products: never overwrite an input, all-or-nothing output sets, a ``run.json`` manifest.

Every CLI command that writes files opens one :func:`run_products` context for the whole run::

    with fail_on_stemmap_error(), run_products("detect", inputs=[scans], outputs=[out]) as run:
        result = ...                                   # the long computation
        write_observations_csv(run.path(out), result)  # write to the staged path

The contract (docs/reliability.md):

* **Refusal.** An output that is, or resolves to (symlink, hard link, same inode), one of the
  run's inputs, or that lies inside an input folder and already exists, is refused before any
  work with an :class:`OutputError` naming both paths and the command-line options that gave
  them (``--rejected 'a.npz' is the same file as the input SCANS 'a.npz'``, by
  :class:`~stemmap.io._cli_context.PathNames`). An output folder that contains an input
  is refused too (replacing the folder would delete it).
* **Staging.** Every product is written into a staging folder created next to its destination
  (same file system, so the final move is a rename), never to the destination itself. An error,
  an exception or a kill while computing or writing leaves the previous products untouched and
  the staging folder is removed (a SIGKILL leaves a hidden ``.stemmap-stage-*`` folder, never a
  visible file).
* **Commit.** Only when the body succeeded are the products moved into place:

  - an output *folder* (``map --out DIR``, ``demo --out DIR``) that is new, empty or holds only
    a previous run's products (its ``run.json`` lists every entry) is switched as a whole: the
    staged folder and the old one are exchanged by one ``renameat2(RENAME_EXCHANGE)`` call, so a
    reader sees either the complete old set or the complete new set, never a mix;
  - separate output *files* (and a folder holding unrelated files) are switched file by file
    with ``os.replace``. The manifest is first replaced by one with ``status: "committing"``
    and rewritten with ``status: "complete"`` after the last file, so an interruption inside
    that short window is visible and :func:`verify_run` names the files that differ.
* **Manifest.** ``run.json`` (folder outputs) or ``<first output>.run.json`` (file outputs):
  command, argv, parameters, inputs with size and SHA-256, stemmap and library versions,
  outputs with size and SHA-256, status, start and end time (UTC).
* **OS errors** (read-only folder, permission, a file where a folder should be, a folder where
  a file should be, disk full) become one :class:`OutputError` naming the user's path.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import datetime as _dt
import errno
import hashlib
import json
import logging
import os
import platform
import shutil
import sys
import tempfile
import time
import uuid
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from stemmap.errors import StemmapError
from stemmap.io._cli_context import PathNames, cli_parameters
from stemmap.io.atomic import umask_mode

__all__ = [
    "MANIFEST_NAME",
    "OutputError",
    "RunProducts",
    "check_not_input",
    "file_sha256",
    "manifest_path",
    "run_products",
    "verify_run",
]

log = logging.getLogger(__name__)

PathLike = str | os.PathLike[str]

#: Name of the manifest inside an output folder; file outputs get ``<name>.run.json``.
MANIFEST_NAME = "run.json"
#: Manifest schema identifier (bump on incompatible changes).
SCHEMA = "stemmap.run/1"
#: Prefix of staging folders (hidden, next to the destination).
STAGE_PREFIX = ".stemmap-stage-"
#: Distributions whose versions the manifest records when installed.
_LIBRARIES = (
    "numpy",
    "scipy",
    "numba",
    "opencv-python",
    "opencv-python-headless",
    "laspy",
    "lazrs",
    "gtsam",
    "matplotlib",
    "typer",
    "rosbags",
    "shapely",
    "pyproj",
)


class OutputError(StemmapError, OSError):
    """A product cannot be written: it would overwrite an input, or the OS refused the write."""


# --------------------------------------------------------------------------- hashing, versions


#: SHA-256 of files already read by this process, keyed by (device, inode, size, mtime_ns):
#: a run hashes each input once although its manifest is written twice (``committing`` then
#: ``complete``) and the tile engine records the same hashes in its chunk manifest.
_SHA256_SEEN: dict[tuple[int, int, int, int], str] = {}


def file_sha256(path: PathLike, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file, read in ``chunk``-byte blocks (bounded memory).

    Memoised per process on the file's identity and modification time, so a file that is
    unchanged is read once however many manifests record it.
    """
    st = os.stat(path)
    key = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    if key in _SHA256_SEEN:
        return _SHA256_SEEN[key]
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while True:
            b = fh.read(chunk)
            if not b:
                break
            h.update(b)
    if len(_SHA256_SEEN) >= 4096:  # bounded: a long-lived process hashing many files
        _SHA256_SEEN.clear()
    _SHA256_SEEN[key] = h.hexdigest()
    return _SHA256_SEEN[key]


def _describe(path: Path, base: Path | None = None) -> dict[str, Any]:
    """Path, kind, size and SHA-256 of a file, or of every file of a folder (sorted)."""
    shown = str(path)
    if base is not None:
        with contextlib.suppress(ValueError):
            shown = str(path.relative_to(base))
    if path.is_dir():
        files = sorted(p for p in path.rglob("*") if p.is_file())
        h = hashlib.sha256()
        size = 0
        for p in files:
            digest = file_sha256(p)
            h.update(f"{p.relative_to(path).as_posix()}\0{digest}\n".encode())
            size += p.stat().st_size
        return {
            "path": shown,
            "kind": "folder",
            "files": len(files),
            "size": size,
            "sha256": h.hexdigest(),
        }
    st = path.stat()
    return {"path": shown, "kind": "file", "size": st.st_size, "sha256": file_sha256(path)}


def _versions() -> dict[str, str]:
    from importlib import metadata

    out: dict[str, str] = {}
    for name in _LIBRARIES:
        with contextlib.suppress(metadata.PackageNotFoundError):
            out[name] = metadata.version(name)
    return out


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


# --------------------------------------------------------------------------- refusal rules


def _within(child: Path, parent: Path) -> bool:
    try:
        child.relative_to(parent)
    except ValueError:
        return False
    return True


def check_not_input(
    output: PathLike, inputs: Iterable[PathLike], *, names: PathNames | None = None
) -> None:
    """OutputError if ``output`` is, or resolves to, one of ``inputs`` (or a file inside one).

    Symlinks are resolved; an existing output is compared by device and inode
    (:func:`os.path.samefile`), which also catches hard links. The message names the
    command-line option or argument that gave each path (``names``, by default the running
    command's, :class:`~stemmap.io._cli_context.PathNames`).
    """
    names = PathNames.from_context() if names is None else names
    out = Path(output)
    out_real = out.resolve()
    shown = names.output(out)
    for inp in inputs:
        ip = Path(inp)
        if not ip.exists():
            continue
        in_real = ip.resolve()
        same = out_real == in_real
        if not same and out.exists():
            with contextlib.suppress(OSError):
                same = os.path.samefile(out, ip)
        if same:
            how = ""
            if out_real != in_real:
                how = " (a hard link to it)"
            elif out.is_symlink() or out.absolute() != out_real:
                how = f" (it resolves to {str(out_real)!r})"
            raise OutputError(
                f"{shown} is the same file as {names.input(ip)}{how}; refusing to overwrite "
                "an input. Choose another output path."
            )
        if ip.is_dir() and out.exists() and _within(out_real, in_real):
            raise OutputError(
                f"{shown} is a file of {names.input(ip, 'input folder')}; refusing to "
                "overwrite an input. Choose another output path."
            )
        if out.is_dir() and _within(in_real, out_real):
            raise OutputError(
                f"{shown} is a folder that contains {names.input(ip)}; writing the run's "
                "products there would replace it. Choose another output folder."
            )


def _os_error(exc: OSError, shown: str, doing: str) -> OutputError:
    """One sentence for an OS error while ``doing`` something to ``shown`` (a path as
    :class:`PathNames` names it: ``--out 'x.csv'``)."""
    reason = exc.strerror or str(exc)
    hint = {
        errno.ENOSPC: " (the disk is full: free space or write elsewhere)",
        errno.EDQUOT: " (disk quota exceeded)",
        errno.EROFS: " (the file system is read-only: write elsewhere)",
        errno.EACCES: " (no permission: write elsewhere or fix the permissions)",
        errno.EPERM: " (not permitted: write elsewhere or fix the permissions)",
        errno.ENOTDIR: " (a file stands where a folder should be)",
        errno.EISDIR: " (it is a folder; give a file name)",
    }.get(exc.errno or -1, "")
    return OutputError(f"cannot {doing} {shown}: {reason}{hint}.")


# --------------------------------------------------------------------------- atomic exchange

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths with Linux renameat2(RENAME_EXCHANGE); False if unsupported."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    rc = fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    e = ctypes.get_errno()
    if e in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(e, os.strerror(e), str(b))


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


# --------------------------------------------------------------------------- the run


def manifest_path(outputs: Sequence[PathLike] = (), out_dir: PathLike | None = None) -> Path:
    """Where a run's manifest goes: ``DIR/run.json`` or ``<first output>.run.json``."""
    if out_dir is not None:
        return Path(out_dir) / MANIFEST_NAME
    if not outputs:
        raise ValueError("a run needs an output folder or at least one output file")
    first = Path(outputs[0])
    return first.with_name(first.name + ".run.json")


def _owned(folder: Path) -> bool:
    """True if ``folder`` is empty or holds only what its run.json lists (safe to replace)."""
    entries = {p.name for p in folder.iterdir()}
    if not entries:
        return True
    m = folder / MANIFEST_NAME
    if not m.is_file():
        return False
    try:
        doc = json.loads(m.read_text(encoding="utf-8"))
        listed = {Path(o["path"]).parts[0] for o in doc.get("outputs", [])}
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return False
    return entries <= listed | {MANIFEST_NAME}


def _replaceable_folder(folder: Path) -> bool:
    """True if a folder *product* (``io convert-scans --out NAME``: a ROS 2 bag folder) may
    replace ``folder``: it is empty, or it is still what an earlier run wrote -- the manifest
    beside it (``NAME.run.json``) lists it as a folder output with the same file count and
    size. Anything else (``--out ~/data``, a bag recorded by ros2 bag) would be deleted."""
    try:
        if not any(folder.iterdir()):
            return True
    except OSError:
        return False
    m = folder.with_name(folder.name + ".run.json")
    try:
        doc = json.loads(m.read_text(encoding="utf-8"))
        for o in doc.get("outputs", []):
            p = Path(o["path"])
            p = p if p.is_absolute() else m.absolute().parent / p
            if o.get("kind") == "folder" and p.absolute() == folder.absolute():
                now = _describe_counts(folder)
                return now == (o.get("files"), o.get("size"))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False
    return False


def _describe_counts(folder: Path) -> tuple[int, int]:
    """(files, bytes) of a folder, as :func:`_describe` counts them, without hashing."""
    files = [p for p in folder.rglob("*") if p.is_file()]
    return len(files), sum(p.stat().st_size for p in files)


@dataclass
class RunProducts:
    """The staged products of one run (use :func:`run_products`, not this class directly)."""

    command: str
    inputs: list[Path]
    out_dir: Path | None
    outputs: list[Path]
    started: str = field(default_factory=_now)
    extra: dict[str, Any] = field(default_factory=dict)
    _t0: float = field(default_factory=time.perf_counter)
    _stages: dict[Path, Path] = field(default_factory=dict)  # destination parent -> staging dir
    _staged: dict[Path, Path] = field(default_factory=dict)  # final path -> staged path
    _dir_stage: Path | None = None
    _swap: bool = False
    #: which command-line option gave each path (for the messages)
    names: PathNames = field(default_factory=PathNames.from_context)

    # ---- setup
    def _open(self) -> None:
        self._check_distinct()
        if self.out_dir is not None:
            self._open_dir(self.out_dir)
        for o in list(self.outputs):
            self._declare(o)

    def _open_dir(self, d: Path) -> None:
        check_not_input(d, self.inputs, names=self.names)
        if d.exists() and not d.is_dir():
            raise OutputError(
                f"{self.names.output(d)} is a file, but must be a folder; remove it or "
                "choose another path."
            )
        parent = d.absolute().parent
        self._mkparent(parent, d)
        self._swap = not d.exists() or _owned(d)
        if self._swap:
            try:
                self._dir_stage = Path(
                    tempfile.mkdtemp(prefix=f".{d.name}{STAGE_PREFIX}", dir=parent)
                )
            except OSError as exc:
                raise _os_error(exc, self.names.output(d), "write the output folder") from exc
        else:
            log.warning(
                "%s holds files of other programs: products are replaced one by one "
                "(not as one folder switch)",
                d,
            )
            self._dir_stage = self._stage_for(d.absolute(), d)
        # mkdtemp makes a 0700 folder: the products get the old folder's mode, or for a new
        # folder the mode mkdir would give (0777 less the umask), so others can read them
        with contextlib.suppress(OSError):
            bits = d.stat().st_mode & 0o7777 if d.exists() else umask_mode(0o777)
            os.chmod(self._dir_stage, bits)

    def _check_distinct(self) -> None:
        """OutputError if two outputs, or an output and the run's manifest, are one file:
        the later product would silently replace the earlier one (``detect --out x.csv
        --rejected x.csv``, ``stems --out s.csv --metrics s.csv.run.json``)."""
        manifest = (
            None if self.out_dir is not None or not self.outputs else manifest_path(self.outputs)
        )
        seen: dict[Path, Path] = {}
        for o in self.outputs:
            if manifest is not None and o.resolve() == manifest.resolve():
                raise OutputError(
                    f"{self.names.output(o)} is where the run's manifest goes (the manifest of "
                    f"{self.names.output(self.outputs[0])}); give it another path."
                )
            first = seen.setdefault(o.resolve(), o)
            if first is not o:
                both = " and ".join(self.names.outputs([first, o]))
                raise OutputError(
                    f"the same file is given twice, as {both}: one product would overwrite "
                    "the other. Give each product its own path."
                )

    def _mkparent(self, parent: Path, shown: Path) -> None:
        for anc in (parent, *parent.parents):
            if anc.exists() and not anc.is_dir():
                raise OutputError(
                    f"cannot write {self.names.output(shown)}: {str(anc)!r} is a file where a "
                    "folder should be."
                )
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise _os_error(exc, self.names.output(shown), "create the folder of") from exc

    def _stage_for(self, parent: Path, shown: Path) -> Path:
        if parent not in self._stages:
            try:
                self._stages[parent] = Path(tempfile.mkdtemp(prefix=STAGE_PREFIX, dir=parent))
            except OSError as exc:
                raise _os_error(exc, self.names.output(shown), "write") from exc
        return self._stages[parent]

    def _declare(self, o: Path) -> Path:
        if self.out_dir is not None and _within(o.absolute(), self.out_dir.absolute()):
            assert self._dir_stage is not None
            rel = o.absolute().relative_to(self.out_dir.absolute())
            staged = self._dir_stage / rel
            staged.parent.mkdir(parents=True, exist_ok=True)
            self._staged[o] = staged
            return staged
        check_not_input(o, self.inputs, names=self.names)
        if o.is_dir() and o.suffix:
            # a folder product (a suffix-less ROS2 bag) may replace a folder; a file may not
            raise OutputError(
                f"cannot write {self.names.output(o)}: it is a folder; give a file name."
            )
        if o.is_dir() and not _replaceable_folder(o):
            raise OutputError(
                f"cannot write {self.names.output(o)}: it is a folder holding files this "
                "command did not write there (the product would replace the whole folder); "
                "give a new folder name, or remove the folder first."
            )
        parent = o.absolute().parent
        self._mkparent(parent, o)
        staged = self._stage_for(parent, o) / o.name
        self._staged[o] = staged
        if o not in self.outputs:
            self.outputs.append(o)
        return staged

    # ---- public API
    def path(self, final: PathLike) -> Path:
        """The staged path to write the product that ends up at ``final`` after the commit."""
        f = Path(final)
        return self._staged[f] if f in self._staged else self._declare(f)

    @property
    def dir(self) -> Path:
        """The staged output folder (folder runs only): write ``run.dir / "trees.csv"``."""
        if self._dir_stage is None:
            raise ValueError("this run has no output folder")
        return self._dir_stage

    def add_input(self, path: PathLike) -> None:
        """Record an input discovered during the run (it is also protected from overwriting)."""
        p = Path(path)
        if p not in self.inputs:
            self.inputs.append(p)
            for o in self.outputs:
                check_not_input(o, [p], names=self.names)

    def note(self, **fields: Any) -> None:
        """Extra JSON-serialisable fields for the manifest (e.g. a metrics summary)."""
        self.extra.update(fields)

    # ---- manifest
    def _manifest(self, status: str, out_entries: list[dict[str, Any]]) -> dict[str, Any]:
        import stemmap

        params = cli_parameters()
        return {
            "schema": SCHEMA,
            "status": status,
            "command": self.command,
            "argv": list(sys.argv),
            "parameters": params,
            "cwd": os.getcwd(),
            "started_utc": self.started,
            "finished_utc": _now(),
            "duration_s": round(time.perf_counter() - self._t0, 3),
            "mode": "folder-switch" if self._swap else "per-file",
            "stemmap_version": stemmap.__version__,
            "python": platform.python_version(),
            "platform": platform.platform(),
            "libraries": _versions(),
            "inputs": [_describe(p) for p in self.inputs if p.exists()],
            "outputs": out_entries,
            **({"extra": self.extra} if self.extra else {}),
        }

    def _out_entries(self, base: Path | None) -> list[dict[str, Any]]:
        entries: list[dict[str, Any]] = []
        if self._swap and self._dir_stage is not None:
            for p in sorted(self._dir_stage.iterdir()):
                if p.name != MANIFEST_NAME:
                    e = _describe(p, self._dir_stage)
                    entries.append(e)
        staged_files = [
            (f, s) for f, s in self._staged.items() if not (self._swap and _within_stage(s, self))
        ]
        for final, staged in staged_files:
            if not staged.exists():
                continue
            e = _describe(staged)
            e["path"] = str(final if base is None else _rel(final, base))
            entries.append(e)
        return entries

    def _write_json(self, path: Path, doc: dict[str, Any]) -> None:
        tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=1, default=str)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)

    # ---- commit / abort
    def _collect_dir(self) -> None:
        """Per-file folder runs: register what the body wrote straight into ``run.dir``."""
        if self._swap or self.out_dir is None or self._dir_stage is None:
            return
        for p in sorted(self._dir_stage.iterdir()):
            self._staged.setdefault(self.out_dir / p.name, p)

    def _commit(self) -> Path | None:
        if not self.outputs and self.out_dir is None:
            return None  # nothing written (e.g. an optional --json not given)
        mpath = manifest_path(self.outputs, self.out_dir)
        self._collect_dir()
        if self._swap:
            assert self.out_dir is not None and self._dir_stage is not None
            doc = self._manifest("complete", self._out_entries(self.out_dir.absolute()))
            self._write_json(self._dir_stage / MANIFEST_NAME, doc)
            self._commit_other_files()
            d = self.out_dir
            if d.exists():
                if not _exchange(self._dir_stage, d):
                    old = d.with_name(f".{d.name}.stemmap-old-{uuid.uuid4().hex[:8]}")
                    os.rename(d, old)
                    os.rename(self._dir_stage, d)
                    self._dir_stage = old
                _remove(self._dir_stage)  # now the previous set
            else:
                os.rename(self._dir_stage, d)
            self._dir_stage = None
            _fsync_dir(d.absolute().parent)
            return mpath
        base = mpath.absolute().parent
        entries = self._out_entries(base)
        # journal: the old manifest is replaced by one saying the set is being switched
        self._write_json(mpath, self._manifest("committing", entries))
        self._commit_other_files()
        self._write_json(mpath, self._manifest("complete", entries))
        _fsync_dir(base)
        return mpath

    def _commit_other_files(self) -> None:
        for final, staged in self._staged.items():
            if self._swap and _within_stage(staged, self):
                continue
            if not staged.exists():
                continue
            if staged.is_dir() and final.is_dir():
                old = staged.with_name(staged.name + ".old")
                os.rename(final, old)
                os.rename(staged, final)
            else:
                os.replace(staged, final)
        for stage in self._stages.values():
            _remove(stage)
        self._stages.clear()

    def _abort(self) -> None:
        for stage in self._stages.values():
            _remove(stage)
        self._stages.clear()
        if self._dir_stage is not None and self._swap:
            _remove(self._dir_stage)
        self._dir_stage = None

    def _final_name(self, p: Any) -> str | None:
        """Map a staged path in an OS error back to the user's path."""
        if p is None:
            return None
        p = os.fsdecode(p) if isinstance(p, (bytes, os.PathLike)) else str(p)
        sp = Path(p)
        for final, staged in self._staged.items():
            if sp == staged or _within(sp, staged):
                return str(final)
        ds = self._dir_stage
        if ds is not None and self.out_dir is not None and _within(sp, ds):
            return str(self.out_dir / sp.relative_to(ds))
        for parent, stage in self._stages.items():
            if _within(sp, stage):
                return str(parent / sp.relative_to(stage))
        return p


def _within_stage(p: Path, run: RunProducts) -> bool:
    return run._dir_stage is not None and _within(p, run._dir_stage)


def _rel(p: Path, base: Path) -> Path:
    try:
        return p.absolute().relative_to(base)
    except ValueError:
        return p.absolute()


@contextlib.contextmanager
def run_products(
    command: str,
    *,
    inputs: Iterable[PathLike | None] = (),
    outputs: Iterable[PathLike | None] = (),
    out_dir: PathLike | None = None,
) -> Iterator[RunProducts]:
    """Stage a run's products and switch them into place only if the whole run succeeds.

    Parameters
    ----------
    command : str
        The command name recorded in the manifest (``"detect"``, ``"map"``, ...).
    inputs : paths
        Files or folders the run reads (``None`` entries are ignored). Outputs resolving to one
        of them are refused; they are hashed into the manifest.
    outputs : paths
        Output files (``None`` entries ignored). Write each via ``run.path(final)``.
    out_dir : path, optional
        An output folder; write its products under ``run.dir``.

    Raises
    ------
    OutputError
        An output is an input, or the OS refused a write (the message names the path).
    """
    inputs, outputs = list(inputs), [*outputs, out_dir]
    run = RunProducts(
        command=command,
        inputs=[Path(p) for p in inputs if p is not None],
        out_dir=None if out_dir is None else Path(out_dir),
        outputs=[Path(p) for p in outputs[:-1] if p is not None],
        names=PathNames.from_context(inputs, outputs),
    )
    try:
        run._open()
        yield run
        run._commit()
    except OutputError:
        run._abort()
        raise
    except OSError as exc:
        run._abort()
        name = run._final_name(exc.filename)
        first = run.out_dir or (run.outputs[0] if run.outputs else None)
        if name is None:
            shown = "the output" if first is None else run.names.output(first)
            raise _os_error(exc, shown, "write") from exc
        if name == exc.filename and not any(str(o) == name for o in run.outputs):
            # not one of the products: an input or a temporary file
            raise _os_error(exc, run.names.named(Path(name)), "access") from exc
        raise _os_error(exc, run.names.output(Path(name)), "write") from exc
    except BaseException:
        run._abort()
        raise


def verify_run(manifest: PathLike) -> list[str]:
    """Problems of a product set: [] if ``manifest`` says complete and every hash matches."""
    m = Path(manifest)
    try:
        doc = json.loads(m.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        return [f"manifest {str(m)!r} is unreadable: {exc}"]
    problems: list[str] = []
    if doc.get("status") != "complete":
        problems.append(f"status is {doc.get('status')!r}, not 'complete'")
    base = m.absolute().parent
    for o in doc.get("outputs", []):
        p = Path(o["path"])
        p = p if p.is_absolute() else base / p
        if not p.exists():
            problems.append(f"{str(p)!r} is missing")
            continue
        if _describe(p)["sha256"] != o.get("sha256"):
            problems.append(f"{str(p)!r} differs from the manifest (another run's file?)")
    return problems
