"""LAS/LAZ tiles: header-only inspection, chunked reading into :class:`PointTile`, atomic writing.

Reading goes through laspy with the multi-threaded lazrs backend, in chunks, so a bounding-box
read of a large tile never holds more than one chunk of unwanted points. Every laspy/lazrs failure
becomes a :class:`FormatError` naming the file, because a surveyor with 2000 tiles needs to know
which one is broken.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np
import pyproj

from railtraj.data import PointTile
from railtraj.errors import FormatError
from railtraj.io.atomic import atomic_path
from railtraj.io.trajectory_csv import require_file

BACKEND = laspy.LazBackend.LazrsParallel
#: Errors laspy and lazrs raise on corrupt, truncated or foreign files (lazrs.LazrsError is a
#: RuntimeError; a short uncompressed LAS gives a ValueError from numpy; a header cut short
#: inside a field gives a struct.error; a corrupt record length a MemoryError).
_READ_ERRORS = (laspy.errors.LaspyException, RuntimeError, ValueError, OSError, EOFError,
                struct.error, MemoryError)
#: GPS week seconds are below this; adjusted standard GPS time (GPS time - 1e9) is far above it.
_WEEK_SECONDS = 604800.0


@dataclass(frozen=True)
class TileHeader:
    """What a tile's header says, read without touching its points."""

    path: Path
    point_count: int
    mins: np.ndarray
    maxs: np.ndarray
    scales: np.ndarray
    offsets: np.ndarray
    point_format: int
    version: str
    has_gps_time: bool
    crs: pyproj.CRS | None = None
    crs_error: str = ""  # why the CRS record could not be parsed ("" if it could, or is absent)

    @property
    def name(self) -> str:
        """The file name, used as the tile's id in outputs."""
        return self.path.name


def _corrupt(path: Path, err: Exception) -> FormatError:
    return FormatError(f"LAS/LAZ file {path} cannot be read ({type(err).__name__}: {err}): it is "
                       "truncated or corrupt; re-export or re-copy it, or remove it from tiles/")


def missing_gps_time_error(path: Path, point_format: int) -> FormatError:
    """The error for a tile whose point format has no gps_time (shared with survey discovery)."""
    return FormatError(
        f"LAS/LAZ file {path}: point format {point_format} has no gps_time; railtraj needs "
        "per-point GPS time to tie points to the trajectory: export the tiles with a point "
        "format that carries gps_time (1, 3, 5, 6-10)")


def empty_tile_error(path: Path) -> FormatError:
    """The error for a tile whose header says it holds no points (its bounds are meaningless)."""
    return FormatError(f"LAS/LAZ file {path} is empty (0 points): remove it from tiles/, or "
                       "re-export the tile if it should hold points")


def _header_info(path: Path, h: laspy.LasHeader) -> TileHeader:
    crs, crs_error = None, ""
    try:
        crs = h.parse_crs()
    except Exception as err:  # noqa: BLE001 - a broken CRS record must not stop reading the points
        crs_error = f"{type(err).__name__}: {err}".splitlines()[0]
    return TileHeader(
        path=path, point_count=int(h.point_count), mins=np.array(h.mins, dtype=np.float64),
        maxs=np.array(h.maxs, dtype=np.float64), scales=np.array(h.scales, dtype=np.float64),
        offsets=np.array(h.offsets, dtype=np.float64), point_format=int(h.point_format.id),
        version=str(h.version), has_gps_time="gps_time" in h.point_format.dimension_names,
        crs=crs, crs_error=crs_error)


def _check_record_counts(p: Path) -> None:
    """Refuse a header whose (E)VLR or LAZ chunk count the file cannot hold: laspy would loop
    over billions of empty records, and lazrs abort the process allocating a chunk table."""
    size = p.stat().st_size
    with open(p, "rb") as f:
        head = f.read(247)
        if head[:4] != b"LASF" or len(head) < 105:
            return  # laspy names what is wrong with such a file
        counts = [("VLRs", struct.unpack_from("<I", head, 100)[0], 54)]
        if len(head) >= 247 and head[25] >= 4:
            counts.append(("EVLRs", struct.unpack_from("<I", head, 243)[0], 60))
        if head[104] & 0x80:  # compressed: the LAZ chunk table offset opens the point data
            f.seek(struct.unpack_from("<I", head, 96)[0])
            table = f.read(8)
            offset = struct.unpack("<q", table)[0] if len(table) == 8 else -1
            if 0 <= offset <= size - 8:
                f.seek(offset + 4)
                counts.append(("LAZ chunks", struct.unpack("<I", f.read(4))[0], 8))
    for kind, n, record in counts:
        if n * record > size:
            raise _corrupt(p, ValueError(f"header says {n} {kind} but the file has only {size} "
                                         "bytes"))


def read_header(path: str | os.PathLike) -> TileHeader:
    """The header of a LAS/LAZ file (bounds, counts, format, CRS); points are not read."""
    p = require_file(path, "LAS/LAZ file")
    _check_record_counts(p)
    try:
        with laspy.open(p) as f:
            return _header_info(p, f.header)
    except _READ_ERRORS as err:
        raise _corrupt(p, err) from None


def read_tile(path: str | os.PathLike, run_id: str = "", chunk_size: int = 2_000_000,
              bbox: tuple[np.ndarray, np.ndarray] | None = None) -> PointTile:
    """Read a tile's coordinates, gps_time and intensity, optionally only inside ``bbox``.

    ``bbox`` is ``(min_xyz, max_xyz)`` (inclusive); it is applied per chunk of ``chunk_size``
    points so memory stays bounded by the chunk plus the kept points.
    """
    p = require_file(path, "LAS/LAZ file")
    _check_record_counts(p)
    lo, hi = (None, None) if bbox is None else (np.asarray(bbox[0], float), np.asarray(bbox[1], float))
    xyz, times, inten = [], [], []
    try:
        with laspy.open(p, laz_backend=BACKEND) as f:
            head = _header_info(p, f.header)
            if not head.has_gps_time:
                raise missing_gps_time_error(p, head.point_format)
            outside = lo is not None and head.point_count and (
                (head.maxs < lo).any() or (head.mins > hi).any())
            n_read = 0
            for chunk in ([] if outside else f.chunk_iterator(chunk_size)):
                n_read += len(chunk)
                c_xyz = np.column_stack([np.asarray(chunk.x), np.asarray(chunk.y),
                                         np.asarray(chunk.z)])
                keep = slice(None) if lo is None else ((c_xyz >= lo) & (c_xyz <= hi)).all(axis=1)
                xyz.append(c_xyz[keep])
                times.append(np.asarray(chunk.gps_time, dtype=np.float64)[keep])
                inten.append(np.asarray(chunk.intensity, dtype=np.uint16)[keep])
    except _READ_ERRORS as err:
        raise _corrupt(p, err) from None
    if not outside and n_read != head.point_count:
        raise _corrupt(p, EOFError(f"header says {head.point_count} points, file holds {n_read}"))
    tile = PointTile(
        xyz=np.concatenate(xyz) if xyz else np.zeros((0, 3)),
        gps_time=np.concatenate(times) if times else np.zeros(0),
        intensity=np.concatenate(inten) if inten else np.zeros(0, np.uint16),
        run_id=run_id, name=p.name)
    if not (np.isfinite(tile.xyz).all() and np.isfinite(tile.gps_time).all()):
        raise FormatError(f"LAS/LAZ file {p} has non-finite coordinates or gps_time after "
                          "scaling: its header scales/offsets are corrupt; re-export it")
    return tile


def _new_header(path: Path, tile: PointTile, scales, offsets,
                template: TileHeader | None) -> laspy.LasHeader:
    if template is not None:
        hdr = laspy.LasHeader(point_format=template.point_format, version=template.version)
        scales, offsets = template.scales, template.offsets
    else:
        hdr = laspy.LasHeader(point_format=6, version="1.4")
        if offsets is None:
            offsets = np.floor(tile.bounds[0]) if len(tile) else np.zeros(3)
    hdr.scales = np.asarray(scales, dtype=np.float64)
    hdr.offsets = np.asarray(offsets, dtype=np.float64)
    if "gps_time" not in hdr.point_format.dimension_names:
        raise missing_gps_time_error(path, hdr.point_format.id)
    week = len(tile) > 0 and 0.0 <= tile.gps_time.min() and tile.gps_time.max() < _WEEK_SECONDS
    hdr.global_encoding.gps_time_type = (laspy.header.GpsTimeType.WEEK_TIME if week
                                         else laspy.header.GpsTimeType.STANDARD)
    return hdr


def write_tile(path: str | os.PathLike, tile: PointTile, scales=(0.001, 0.001, 0.001),
               offsets=None, crs: str | pyproj.CRS | None = None,
               template: TileHeader | None = None) -> None:
    """Write ``tile`` atomically as LAS (``.las``) or compressed LAZ (``.laz``).

    Default: point format 6, LAS 1.4, 1 mm scale, offsets at the floor of the minimum corner.
    ``template`` (e.g. the input tile's header) supplies format, version, scales and offsets
    instead. The gps_time type flag is "standard" unless every time is a GPS week second
    (0-604800 s), which is flagged "week" so the header tells the truth about the clock.
    """
    hdr = _new_header(Path(path), tile, scales, offsets, template)
    q = np.round((tile.xyz - hdr.offsets) / hdr.scales)
    if len(tile) and np.abs(q).max() > np.iinfo(np.int32).max:
        raise FormatError(f"cannot write {path}: coordinates do not fit LAS 32-bit integers with "
                          f"scales {hdr.scales} and offsets {hdr.offsets}; use offsets near the "
                          "data (offsets=None) or a coarser scale")
    if crs is not None:
        hdr.add_crs(pyproj.CRS.from_user_input(crs))
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = tile.xyz[:, 0], tile.xyz[:, 1], tile.xyz[:, 2]
    las.gps_time = tile.gps_time
    if tile.intensity is not None:
        las.intensity = tile.intensity
    compress = Path(path).suffix.lower() == ".laz"
    with atomic_path(path) as tmp:
        las.write(tmp, do_compress=compress, laz_backend=BACKEND if compress else None)
