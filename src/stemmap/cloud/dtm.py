"""Digital terrain model (DTM) of a cloud as a GeoTIFF (ours; the product of lidR's
``rasterize_terrain``, 3DFin's and FSCT's DTM outputs).

The DTM is the ground raster that ``stemmap stems`` measures heights from
(:class:`~stemmap.cloud.ground.GroundModel`: cell minima cleaned of trunks, shrubs and low
outliers, a local plane through the 3 x 3 lowest points evaluated at each cell centre), built
in one streaming pass over the cloud and written as a single-band float32 GeoTIFF:

* one pixel per ground cell (``StemConfig.ground_cell``, 1 m by default), the value is the
  ground height z (the cloud's vertical unit, metres) at the pixel centre;
* pixels of cells that held no point at all are nodata (:data:`DTM_NODATA`): the ground there
  is not measured (decision: no interpolation beyond one cell into scan shadows or outside the
  plot; lidR interpolates over the whole hull);
* the CRS is the cloud's (``--crs`` or the LAS header), else a local engineering CRS naming
  the cloud's frame (:func:`~stemmap.io.geo.local_crs`), so GIS tools do not read metres as
  degrees.

A cloud without ground (one tree exported by 3DFin, TreeQSM, ITSMe) and a single 2D slice
have no terrain: asking for their DTM is an error.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.cloud.ground import BASE_GROUND, DEFAULT_MAX_MEMORY, GroundAccumulator, GroundModel
from stemmap.errors import InputError

__all__ = ["DTM_NODATA", "ground_of_file", "require_terrain", "write_dtm"]

log = logging.getLogger(__name__)

#: nodata value of the DTM GeoTIFF (cells without points)
DTM_NODATA = -9999.0


def ground_of_file(
    path: str | os.PathLike[str],
    cell: float = 1.0,
    max_diameter: float = 2.0,
    *,
    chunk_size: int = 2_000_000,
    topic: str | None = None,
    max_memory: float = DEFAULT_MAX_MEMORY,
) -> GroundModel:
    """The ground model of a cloud file, streamed in chunks of ``chunk_size`` points.

    Raises
    ------
    InputError
        The cloud has no ground: its lowest points fit inside one stem of ``max_diameter``
        metres (one segmented tree, :meth:`GroundAccumulator.stem_base`), or it is one thin
        slice (z range under 1 m).
    """
    from stemmap.io.clouds import iter_cloud_chunks

    acc = GroundAccumulator(cell, max_memory)
    zmin, zmax = np.inf, -np.inf
    for chunk in iter_cloud_chunks(path, chunk_size, topic=topic):
        if len(chunk.xyz):
            acc.update(chunk.xyz)
            zmin = min(zmin, float(chunk.xyz[:, 2].min()))
            zmax = max(zmax, float(chunk.xyz[:, 2].max()))
    if not np.isfinite(zmin):
        raise InputError(f"{path}: the cloud holds no points, so it has no terrain model.")
    if zmax - zmin < 1.0:
        _no_ground(path, f"it is one slice (z range {zmax - zmin:.2f} m)")
    if acc.stem_base(max_diameter) is not None:
        _no_ground(path, _ONE_TREE)
    return acc.model()


_ONE_TREE = "its lowest points fit inside one stem: one segmented tree"


def _no_ground(source: object, why: str) -> None:
    raise InputError(f"{source}: the cloud has no ground ({why}), so no DTM; leave out --dtm.")


def require_terrain(ground: GroundModel | None, source: object) -> GroundModel:
    """The ground model a detection run measured heights from
    (:func:`stemmap.cloud.stems.detect_stems_file`'s ``on_ground``) as a terrain for
    :func:`write_dtm`; the same refusals as :func:`ground_of_file`.

    Raises
    ------
    InputError
        ``None`` (the cloud was read as one slice) or a flat base at a lone stem's lowest
        points (one segmented tree).
    """
    if ground is None:
        _no_ground(source, "it is read as one slice (z range under 1 m)")
    elif ground.base != BASE_GROUND:
        _no_ground(source, _ONE_TREE)
    assert ground is not None
    return ground


def _rasterio_crs(crs: str | None, frame: str) -> Any:
    from rasterio.crs import CRS

    from stemmap.io.geo import local_crs, parse_crs

    pc = local_crs(frame) if crs is None else parse_crs(crs)
    return CRS.from_wkt(pc.to_wkt(version="WKT1_GDAL") or pc.to_wkt())


def write_dtm(
    path: str | os.PathLike[str],
    ground: GroundModel,
    crs: str | None,
    *,
    frame: str = "cloud",
    unit: tuple[str, float] = ("m", 1.0),
) -> None:
    """Write ``ground`` as a float32 GeoTIFF (module doc): north-up, pixel = ground cell,
    value = ground z at the pixel centre, :data:`DTM_NODATA` where no point fell.

    ``unit``: (name, metres per unit) of the CRS the raster is written in, when the cloud was
    read in another unit (``stemmap stems --units us-ft``): the ground model is in metres; the
    raster's grid and heights are written in that unit, as the cloud's own coordinates."""
    import rasterio
    from affine import Affine

    if ground.base != BASE_GROUND:
        raise InputError(
            f"the ground model is a flat base ({ground.base}), not a terrain: no DTM to write."
        )
    u = float(unit[1])
    z = np.asarray(ground.z, dtype=np.float64) / u
    obs = np.ones(z.shape, dtype=bool) if ground.observed is None else ground.observed
    band = np.where(obs, z, DTM_NODATA).astype(np.float32)
    # GroundModel z is indexed [i (x), j (y)] from the lower-left corner; a GeoTIFF's rows run
    # from north to south
    img = band.T[::-1, :]
    nx, ny = z.shape
    ox, oy = ground.origin[0] / u, ground.origin[1] / u
    cell = ground.cell / u
    transform = Affine(cell, 0.0, ox, 0.0, -cell, oy + ny * cell)
    with rasterio.open(
        Path(path),
        "w",
        driver="GTiff",
        width=nx,
        height=ny,
        count=1,
        dtype="float32",
        crs=_rasterio_crs(crs, frame),
        transform=transform,
        nodata=DTM_NODATA,
        compress="deflate",
    ) as dst:
        dst.write(img, 1)
        dst.set_band_description(1, f"ground height z ({unit[0]})")
        dst.update_tags(AREA_OR_POINT="Area", source="stemmap stems --dtm")
    log.info("DTM %s: %d x %d cells of %.2f m, %d without points", path, nx, ny, ground.cell,
             int((~obs).sum()))  # fmt: skip
