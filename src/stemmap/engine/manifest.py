"""Per-chunk results and the chunk manifest of a scaled-out run (resume support).

Layout of a run's work folder::

    <work>/manifest.jsonl       one JSON line per finished or failed chunk, appended in order
    <work>/chunks/<id>.npz      a chunk's result, written atomically (temp file + rename)

A manifest line holds ``chunk``, ``status`` (``done`` / ``failed``), ``inputs`` (path -> content
hash of every tile the buffered chunk reads), ``params`` (hash of the detector configuration
and the chunk geometry), ``seconds``, ``time`` (UTC, ISO 8601), for a done chunk ``result``
(the hash of its result file, :func:`result_hash`) and for a failed chunk ``error``. A chunk
is *done* for ``--resume`` when its last line says ``done`` with the same inputs and params
and its result file exists with the recorded hash.

The manifest is durable (each line fsynced); the result files are not (written atomically,
without fsync): after a power loss a result may be missing, empty or torn although its
line says done, and the hash check sends such a chunk back to be computed
(docs/reliability.md, "Scale-out engine").
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
import re
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

from stemmap.errors import InputError
from stemmap.io._util import check_npz_sizes
from stemmap.io.atomic import atomic_write

__all__ = ["Manifest", "params_hash", "result_hash"]

log = logging.getLogger(__name__)


def params_hash(obj: Any) -> str:
    """Stable hash (BLAKE2b, 128 bit, hex) of a JSON-able value or dataclass."""

    def norm(v: Any) -> Any:
        if is_dataclass(v) and not isinstance(v, type):
            return {"__type__": type(v).__name__, **{k: norm(x) for k, x in asdict(v).items()}}
        if isinstance(v, dict):
            return {str(k): norm(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [norm(x) for x in v]
        if hasattr(v, "tolist"):
            return v.tolist()
        return v

    text = json.dumps(norm(obj), sort_keys=True, default=repr)
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def result_hash(path: str | os.PathLike[str]) -> str:
    """BLAKE2b (128 bit, hex) of a chunk result file's bytes; ``""`` when it is missing or
    unreadable (never equal to a recorded hash)."""
    h = hashlib.blake2b(digest_size=16)
    try:
        with open(path, "rb") as fh:
            while block := fh.read(1 << 20):
                h.update(block)
    except OSError:
        return ""
    return h.hexdigest()


#: What a run keeps in its work folder.
_WORK_ENTRIES = frozenset({"manifest.jsonl", "chunks", "stage"})
#: A chunk id (:func:`~stemmap.engine.catalog.plan_chunks`: ``x3_y-1``, split ``x3_y-1ab``)
#: or the statistics pilot's.
_CHUNK_ID = re.compile(r"pilot|x-?\d+_y-?\d+[a-d]*")


class Manifest:
    """The append-only chunk manifest of one work folder (written by the client only)."""

    def __init__(self, work: str | os.PathLike[str]) -> None:
        self.work = Path(work)
        self.path = self.work / "manifest.jsonl"
        self.chunks = self.work / "chunks"

    def claim(self) -> None:
        """Refuse a work folder that holds anything a run would not have written there.

        A run replaces ``manifest.jsonl``, overwrites ``chunks/<id>.npz`` and removes
        ``stage/`` when it is done, so ``--work ~/data`` or ``--work .`` would delete a
        ``stage`` folder or a ``manifest.jsonl`` of the user's. A new folder, an empty one, or
        an earlier run's work folder (only those three entries, the manifest's first line a
        chunk record, ``stage/`` holding only chunk folders) is accepted.

        Raises
        ------
        InputError
            Naming the folder and what in it is not a work folder's.
        """
        w = self.work
        if not w.exists():
            return
        if not w.is_dir():
            raise InputError(f"work folder {str(w)!r} is a file; give --work a folder.")
        foreign = sorted(p.name for p in w.iterdir() if p.name not in _WORK_ENTRIES)
        stage = w / "stage"
        if stage.is_dir():
            foreign += [
                f"stage/{p.name}"
                for p in sorted(stage.iterdir())
                if not (p.is_dir() and _CHUNK_ID.fullmatch(p.name))
            ]
        elif stage.exists():
            foreign.append("stage")
        if self.path.exists() and not self._is_manifest():
            foreign.append("manifest.jsonl")
        if foreign:
            shown = ", ".join(foreign[:5]) + (", ..." if len(foreign) > 5 else "")
            raise InputError(
                f"work folder {str(w)!r} is not a stemmap work folder: it holds {shown}. A run "
                "replaces its manifest.jsonl, writes chunks/ and removes stage/ when done; give "
                "--work a new or empty folder (or the work folder of an earlier run)."
            )

    def _is_manifest(self) -> bool:
        """The file is empty or its first line is a chunk record (a torn line from a kill too)."""
        try:
            with open(self.path, encoding="utf-8") as fh:
                first = fh.readline(1 << 20)
        except (OSError, UnicodeDecodeError):
            return False
        if not first.strip():
            return True
        try:
            rec = json.loads(first)
        except ValueError:
            return first.startswith('{"chunk": ')  # a line torn by a kill
        return isinstance(rec, dict) and "chunk" in rec

    def result_path(self, chunk_id: str) -> Path:
        return self.chunks / f"{chunk_id}.npz"

    def entries(self) -> dict[str, dict[str, Any]]:
        """The last line of each chunk (a torn last line from a kill is skipped)."""
        out: dict[str, dict[str, Any]] = {}
        if not self.path.exists():
            return out
        for k, line in enumerate(self.path.read_text(encoding="utf-8").splitlines()):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
                out[str(rec["chunk"])] = rec
            except (ValueError, KeyError):
                log.warning("%s line %d is not a manifest record; ignored", self.path, k + 1)
        return out

    def _done(
        self, chunk_id: str, rec: dict[str, Any] | None, inputs: dict[str, str], params: str
    ) -> bool:
        return (
            rec is not None
            and rec.get("status") == "done"
            and rec.get("inputs") == inputs
            and rec.get("params") == params
            and bool(rec.get("result"))
            and rec.get("result") == result_hash(self.result_path(chunk_id))
        )

    def is_done(self, chunk_id: str, inputs: dict[str, str], params: str) -> bool:
        return self._done(chunk_id, self.entries().get(chunk_id), inputs, params)

    def done_set(self, wanted: dict[str, tuple[dict[str, str], str]]) -> set[str]:
        """Ids among ``wanted`` (id -> (inputs, params)) already done with matching hashes
        (inputs, parameters and the result file's bytes)."""
        ent = self.entries()
        return {
            cid
            for cid, (inputs, params) in wanted.items()
            if self._done(cid, ent.get(cid), inputs, params)
        }

    def append(
        self,
        chunk_id: str,
        status: str,
        inputs: dict[str, str],
        params: str,
        *,
        seconds: float = float("nan"),
        error: str = "",
        **extra: Any,
    ) -> None:
        """Append one line (one ``write`` of a whole line, flushed and fsynced)."""
        rec: dict[str, Any] = {
            "chunk": chunk_id,
            "status": status,
            "inputs": inputs,
            "params": params,
            "seconds": round(seconds, 3) if seconds == seconds else None,
            "time": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            **extra,
        }
        if error:
            rec["error"] = error
        self.work.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(rec, sort_keys=True) + "\n")
            fh.flush()
            os.fsync(fh.fileno())

    def reset(self) -> None:
        """Start a fresh run: drop the manifest (results are overwritten chunk by chunk)."""
        if self.path.exists():
            self.path.unlink()


def save_columns(path: Path, columns: dict[str, Any], *, durable: bool = True) -> None:
    """Write named arrays as an .npz atomically (no pickled objects); ``durable``: fsynced
    (:func:`~stemmap.io.atomic.atomic_write`)."""
    import numpy as np

    with atomic_write(path, "wb", durable=durable) as fh:
        arrays: dict[str, Any] = {k: np.asarray(v) for k, v in columns.items()}
        np.savez(fh, **arrays)


def load_columns(path: Path) -> dict[str, Any]:
    """Read an .npz written by :func:`save_columns` (pickles refused)."""
    import numpy as np

    try:
        with np.load(path, allow_pickle=False) as z:
            check_npz_sizes(z, path, "chunk result")
            return {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise InputError(f"chunk result {str(path)!r} is unreadable ({exc}); rerun it.") from exc
