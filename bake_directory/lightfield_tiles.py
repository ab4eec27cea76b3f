"""Light-field atlas tiles on disk: layout, index, block <-> image conversion (pure numpy).

A tile is one Cycles render: a grid of `columns` x `rows` blocks of R x R pixels, block k (row-major from
the top-left) holding the octahedral light field of the tile's k-th texel (pixel conventions of
shaders/octahedral.py: block row 0 is v = -1). Files, per kind (``lightfield``, ``env_visibility``,
``env_radiance``, ``midpoints``):
  KIND/index.json       resolution, samples, plan hash, and per tile its texels, file name and, where they differ
                        from the index's, its own samples (light fields of objects with lightmaps only)
  KIND/tile_0000.exr    half-float RGB, written atomically; metadata holds the plan and tile hashes
A tile whose file exists with matching hashes is finished: resumed runs and farm machines skip it.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .bake_plan import BakeInputError, write_json_atomic
from .exr_io import ExrError, read_exr, read_exr_metadata

INDEX_NAME = "index.json"
DEFAULT_TILE_MEGAPIXELS = 4.0  # Cycles keeps a few float passes per pixel: ~100 MB per tile at 4 MP


@dataclass
class Tile:
    index: int
    file: str
    columns: int
    rows: int
    texels: list  # [[atlas_row, atlas_col], ...] in block order
    hash: str = ""
    samples: int = 0  # samples per pixel of this tile; 0: the index's
    bounce_left_out: str = "diffuse"  # the scattering its texels' surfaces add in the bake: diffuse or glossy

    def __post_init__(self):
        if not self.hash:
            payload = json.dumps([self.columns, self.rows, self.texels], separators=(",", ":")).encode()
            self.hash = hashlib.sha256(payload).hexdigest()[:16]


@dataclass
class TileIndex:
    kind: str
    plan_hash: str
    resolution: int
    samples: int
    channels: int
    tiles: list = field(default_factory=list)

    def to_dict(self):
        return asdict(self)

    @classmethod
    def from_dict(cls, data):
        tiles = [Tile(**t) for t in data.pop("tiles")]
        return cls(**data, tiles=tiles)


def tile_grid(count: int) -> tuple[int, int]:
    """Columns and rows of a near-square grid holding `count` blocks."""
    columns = max(1, math.ceil(math.sqrt(count)))
    return columns, max(1, math.ceil(count / columns))


def plan_tiles(texels: np.ndarray, resolution: int, *, max_megapixels: float = DEFAULT_TILE_MEGAPIXELS,
               prefix: str = "tile", inputs: np.ndarray | None = None) -> list[Tile]:
    """Split texels (T, 2) into tiles of at most `max_megapixels` of render pixels each. `inputs` (T, ...): what the
    camera renders each texel from (surface points, normals); each tile's hash then covers its share of them, so a
    tile rendered from other inputs (another capture's layout, the held-out midpoints' points) is not taken as
    finished."""
    per_tile = max(1, int(max_megapixels * 1e6) // (resolution * resolution))
    tiles = []
    for index, start in enumerate(range(0, len(texels), per_tile)):
        chunk = np.asarray(texels[start:start + per_tile]).tolist()
        columns, rows = tile_grid(len(chunk))
        tile = Tile(index, f"{prefix}_{index:04d}.exr", columns, rows, chunk)
        if inputs is not None:
            digest = hashlib.sha256(np.ascontiguousarray(inputs[start:start + per_tile], np.float32).tobytes())
            tile.hash = hashlib.sha256((tile.hash + digest.hexdigest()).encode()).hexdigest()[:16]
        tiles.append(tile)
    return tiles


def parse_share(share: str | None, count: int) -> list[int]:
    """'i/N' -> the tile indices machine i of N renders (every N-th tile, 1-based i); None -> all."""
    if not share:
        return list(range(count))
    try:
        i, n = (int(x) for x in share.split("/"))
    except ValueError:
        raise BakeInputError(f"--tile {share!r}: expected i/N, e.g. 2/8") from None
    if not (1 <= i <= n):
        raise BakeInputError(f"--tile {share!r}: i must be between 1 and N")
    return list(range(i - 1, count, n))


def blocks_to_images(pixels: np.ndarray, columns: int, rows: int, resolution: int, count: int) -> np.ndarray:
    """(rows*R, columns*R, C) tile pixels -> (count, R, R, C) per-texel octahedral images."""
    r = resolution
    c = pixels.shape[-1]
    grid = pixels[:rows * r, :columns * r].reshape(rows, r, columns, r, c).transpose(0, 2, 1, 3, 4)
    return grid.reshape(rows * columns, r, r, c)[:count]


def images_to_blocks(images: np.ndarray, columns: int, rows: int) -> np.ndarray:
    """Inverse of blocks_to_images; missing blocks are zero."""
    count, r, _, c = images.shape
    padded = np.zeros((rows * columns, r, r, c), images.dtype)
    padded[:count] = images
    return padded.reshape(rows, columns, r, r, c).transpose(0, 2, 1, 3, 4).reshape(rows * r, columns * r, c)


def write_index(kind_dir: Path, index: TileIndex) -> None:
    write_json_atomic(Path(kind_dir) / INDEX_NAME, index.to_dict())


def read_index(kind_dir: Path, plan_hash: str | None = None) -> TileIndex:
    path = Path(kind_dir) / INDEX_NAME
    if not path.is_file():
        raise BakeInputError(f"{kind_dir}: no {INDEX_NAME}; run the render stage first")
    index = TileIndex.from_dict(json.loads(path.read_text()))
    if plan_hash is not None and index.plan_hash != plan_hash:
        raise BakeInputError(f"{kind_dir}: rendered for another plan; run the render stage again")
    return index


def tile_is_finished(kind_dir: Path, index: TileIndex, tile: Tile, made_by: dict[str, str] | None = None) -> bool:
    """Whether the tile's file was rendered for this plan, tile, resolution and samples; made_by: metadata that
    must match too (how a pass was made, when that changed and older tiles must be rendered again)."""
    try:
        meta = read_exr_metadata(Path(kind_dir) / tile.file)
    except ExrError:  # missing, truncated or not an EXR: render it (again)
        return False
    return (meta.get("plan_hash") == index.plan_hash and meta.get("tile_hash") == tile.hash
            and meta.get("resolution") == str(index.resolution)
            and meta.get("samples") == str(tile_samples(index, tile))
            and all(meta.get(key) == value for key, value in (made_by or {}).items()))


def tile_samples(index: TileIndex, tile: Tile) -> int:
    return tile.samples or index.samples


def read_images(kind_dir: Path, plan_hash: str | None = None):
    """All tiles of a kind: (texels (T, 2) atlas [row, col], images (T, R, R, C) float32).

    Refuses an incomplete set: a missing tile (an unfinished or partial render) is an error, never zeros."""
    kind_dir = Path(kind_dir)
    index = read_index(kind_dir, plan_hash)
    missing = [t.file for t in index.tiles if not tile_is_finished(kind_dir, index, t)]
    if missing:
        raise BakeInputError(f"{kind_dir}: {len(missing)} of {len(index.tiles)} tiles are not rendered "
                             f"(first: {missing[0]}); run the render stage (all --tile shares) again")
    texels, images = [], []
    for tile in index.tiles:
        try:
            pixels, _, _ = read_exr(kind_dir / tile.file)
        except ExrError as exc:
            raise BakeInputError(str(exc)) from exc
        images.append(blocks_to_images(pixels[..., :index.channels], tile.columns, tile.rows, index.resolution,
                                       len(tile.texels)))
        texels.extend(tile.texels)
    return np.asarray(texels, np.int64), np.concatenate(images).astype(np.float32)


def read_preview_images(kind_dir: Path, plan_hash: str | None, count: int) -> np.ndarray:
    """`count` evenly spaced texels' images (count, R, R, C), reading only the tiles that hold them."""
    kind_dir = Path(kind_dir)
    index = read_index(kind_dir, plan_hash)
    missing = [t.file for t in index.tiles if not tile_is_finished(kind_dir, index, t)]
    if missing or not index.tiles:
        raise BakeInputError(f"{kind_dir}: {len(missing)} of {len(index.tiles)} tiles are not rendered")
    starts = np.cumsum([0] + [len(t.texels) for t in index.tiles])
    wanted = np.unique(np.linspace(0, starts[-1] - 1, num=min(count, starts[-1])).astype(int))
    images = []
    for k, tile in enumerate(index.tiles):
        local = wanted[(wanted >= starts[k]) & (wanted < starts[k + 1])] - starts[k]
        if len(local):
            pixels, _, _ = read_exr(kind_dir / tile.file)
            images.append(blocks_to_images(pixels[..., :index.channels], tile.columns, tile.rows, index.resolution,
                                           len(tile.texels))[local])
    return np.concatenate(images).astype(np.float32)


def preview_mosaic(images: np.ndarray, count: int = 16, gap: int = 1) -> np.ndarray:
    """Up to `count` evenly spaced per-texel images (T, R, R, C) side by side, tone mapped to [0, 1]
    (x / (1 + x), gamma 2.2; one channel shown as grey) with `gap` black pixels between them."""
    if len(images) == 0:
        return np.zeros((1, 1, 3))
    pick = np.unique(np.linspace(0, len(images) - 1, num=min(count, len(images))).astype(int))
    chosen = np.asarray(images[pick], np.float64)
    if chosen.shape[-1] == 1:
        chosen = np.repeat(chosen, 3, axis=-1)
    chosen = np.maximum(np.nan_to_num(chosen), 0.0)
    mapped = (chosen / (1.0 + chosen)) ** (1 / 2.2)
    columns, rows = tile_grid(len(pick))
    r = images.shape[1]
    mosaic = np.zeros((rows * (r + gap) - gap, columns * (r + gap) - gap, 3))
    for k, image in enumerate(mapped):
        y, x = divmod(k, columns)
        mosaic[y * (r + gap):y * (r + gap) + r, x * (r + gap):x * (r + gap) + r] = image
    return mosaic
