"""Scale-out on Dask: tile catalogs with buffered chunks, one task per chunk, manifests, resume.

The only subpackage that knows about Dask (:mod:`stemmap.engine.cluster`); the library
functions it runs stay pure.

* :class:`Catalog` -- LAS/LAZ tiles indexed from their headers (files, folders, globs, list
  files); :func:`plan_chunks` -- a grid of buffered chunks (lidR's LAScatalog semantics),
  split when too dense; :func:`read_chunk` -- a buffered chunk's points in bounded memory.
* :func:`run_stems_catalog` -- stems per chunk (ownership by stem centre), manifest and
  resume, merged result equal to one process over the whole cloud.
* :func:`dask_client`, :func:`run_graph`, :func:`run_tasks` -- a local or remote cluster; a
  graph of tasks (stage, pilot, chunks) or independent tasks, retried, whose
  failures are reported while the others finish.

See docs/algorithms/engine.md.
"""

from stemmap.engine.catalog import Catalog, Chunk, Tile, expand_inputs, plan_chunks, read_chunk
from stemmap.engine.cluster import Dep, TaskOutcome, dask_client, run_graph, run_tasks
from stemmap.engine.manifest import Manifest
from stemmap.engine.stems import (
    DEFAULT_BUFFER,
    MIN_EXACT_BUFFER,
    CatalogRun,
    catalog_statistics,
    merge_chunk_results,
    run_stems_catalog,
    stems_chunk,
)

__all__ = [
    "DEFAULT_BUFFER",
    "MIN_EXACT_BUFFER",
    "Catalog",
    "CatalogRun",
    "Chunk",
    "Dep",
    "Manifest",
    "TaskOutcome",
    "Tile",
    "catalog_statistics",
    "dask_client",
    "expand_inputs",
    "merge_chunk_results",
    "plan_chunks",
    "read_chunk",
    "run_graph",
    "run_stems_catalog",
    "run_tasks",
    "stems_chunk",
]
