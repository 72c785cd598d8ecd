"""The vehicle library: ``assets/vehicles/library.json`` and the meshes it lists.

Contract (format ``"adv3d-vehicle-library"``, version 1; documented in ``docs/formats.md``)::

    {"format": "adv3d-vehicle-library", "version": 1,
     "assets": [{"id", "file", "class", "dimensions": [L, W, H], "in_shape_space",
                 "triangle_count", "source": {...}, "licence": {...},
                 "curation": {...}, "cleaning": {...}}, ...],
     "excluded": [{"pack", "file", "reason"}, ...]}

Mesh files are glTF binaries stored in the glTF frame (Y up); :func:`load_asset_mesh` returns
them in the project convention: metres, +x front, +y left, +z up, origin at the centre of the
footprint on the ground (z = 0 where the tyres touch).

This module imports only numpy / trimesh, so the Blender add-on can use it in-process.
"""
from __future__ import annotations

import copy
import math
import re
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from ..errors import FileFormatError
from ..fileio import REPO_ROOT, check_header, read_json, write_json

FORMAT = "adv3d-vehicle-library"
VERSION = 1
DEFAULT_LIBRARY: Path = REPO_ROOT / "assets" / "vehicles" / "library.json"

#: Classes used in the shipped library (others are allowed: any lower-case identifier).
VEHICLE_CLASSES = ("sedan", "hatchback", "sports", "suv", "van", "pickup", "truck", "bus",
                   "ambulance", "fire_truck", "garbage_truck", "police", "taxi")

_ID_RE = re.compile(r"^[a-z0-9][a-z0-9_.-]*$")
_CLASS_RE = re.compile(r"^[a-z][a-z0-9_]*$")
_ASSET_KEYS = ("id", "file", "class", "dimensions", "in_shape_space", "triangle_count",
               "source", "licence", "curation", "cleaning")
_EXCLUDED_KEYS = ("pack", "file", "reason")


@dataclass(frozen=True)
class VehicleAsset:
    """One curated vehicle mesh.

    Attributes:
        id: unique, file-name-safe identifier (``quaternius-cars.suv``).
        file: mesh path relative to the folder holding library.json (POSIX separators).
        vehicle_class: sedan, hatchback, sports, suv, van, pickup, truck, bus, ...
        dimensions: (length, width, height) in metres of the converted mesh's bounding box.
        source: where it came from: ``pack``, ``file`` (original file name), ``author``, ``url``.
        licence: ``name`` (SPDX id such as ``CC0-1.0``) and ``file`` (licence text, relative to
            the library folder).
        triangle_count: triangles in the stored mesh.
        cleaning: the cleaning report (see :func:`adv3d_runner.shapes.cleaning.clean_mesh`).
        curation: what was done on import: axes, unit scale, original size, scaling and why.
        in_shape_space: whether the PCA shape space is built over this asset.
    """

    id: str
    file: str
    vehicle_class: str
    dimensions: tuple[float, float, float]
    source: dict = field(default_factory=dict)
    licence: dict = field(default_factory=dict)
    triangle_count: int = 0
    cleaning: dict = field(default_factory=dict)
    curation: dict = field(default_factory=dict)
    in_shape_space: bool = True

    def to_json(self) -> dict:
        """The asset as its JSON object (fixed key order)."""
        return {
            "id": self.id,
            "file": self.file,
            "class": self.vehicle_class,
            "dimensions": [float(v) for v in self.dimensions],
            "in_shape_space": bool(self.in_shape_space),
            "triangle_count": int(self.triangle_count),
            "source": copy.deepcopy(self.source),
            "licence": copy.deepcopy(self.licence),
            "curation": copy.deepcopy(self.curation),
            "cleaning": copy.deepcopy(self.cleaning),
        }


@dataclass
class VehicleLibrary:
    """The parsed library: its folder and its assets, in file order.

    Attributes:
        root: folder that asset ``file`` paths are relative to (the folder of library.json).
        assets: the assets.
        excluded: source files deliberately left out, each ``{"pack", "file", "reason"}``.
    """

    root: Path
    assets: list[VehicleAsset] = field(default_factory=list)
    excluded: list[dict] = field(default_factory=list)

    def get(self, asset_id: str) -> VehicleAsset:
        """The asset with this id; ``KeyError`` listing the known ids if absent."""
        for asset in self.assets:
            if asset.id == asset_id:
                return asset
        raise KeyError(f"no asset {asset_id!r} in the library at {self.root} "
                       f"(known: {', '.join(a.id for a in self.assets) or 'none'})")

    def ids(self) -> list[str]:
        return [a.id for a in self.assets]

    def shape_space_assets(self) -> list[VehicleAsset]:
        """Assets the shape space is built over (``in_shape_space``), in library order."""
        return [a for a in self.assets if a.in_shape_space]

    def by_class(self, vehicle_class: str) -> list[VehicleAsset]:
        """Assets of one class, in library order."""
        return [a for a in self.assets if a.vehicle_class == vehicle_class]

    def path_of(self, asset: VehicleAsset | str) -> Path:
        """Absolute path of an asset's mesh file."""
        if isinstance(asset, str):
            asset = self.get(asset)
        return self.root / asset.file

    def put(self, asset: VehicleAsset) -> None:
        """Add ``asset``, or replace the asset with the same id in place (keeps order)."""
        for i, old in enumerate(self.assets):
            if old.id == asset.id:
                self.assets[i] = asset
                return
        self.assets.append(asset)

    def to_json(self) -> dict:
        return {
            "format": FORMAT,
            "version": VERSION,
            "assets": [a.to_json() for a in self.assets],
            "excluded": copy.deepcopy(self.excluded),
        }


# ----------------------------------------------------------------------------- validation

def _require(cond: bool, path: Path | None, where: str, expected: str, got: Any) -> None:
    if not cond:
        raise FileFormatError(path, where, expected, got)


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _check_keys(obj: dict, allowed: tuple[str, ...], required: tuple[str, ...], path, where) -> None:
    for key in required:
        _require(key in obj, path, f"{where}.{key}", "a value (required field)", "missing")
    for key in obj:
        _require(key in allowed, path, f"{where}.{key}", f"no such field (allowed: {', '.join(allowed)})", key)


def _check_rel_file(value: Any, path, where: str) -> str:
    _require(isinstance(value, str) and value != "", path, where, "a relative file path (string)", value)
    p = PurePosixPath(value)
    _require(not p.is_absolute() and ".." not in p.parts and "\\" not in value, path, where,
             "a relative POSIX path inside the library folder (no '..', no absolute path)", value)
    return value


def _check_json_object(value: Any, path, where: str) -> dict:
    _require(isinstance(value, dict), path, where, "a JSON object", value)
    return value


def asset_from_json(obj: Any, path: Path | None = None, where: str = "$") -> VehicleAsset:
    """Validate one asset object and build the :class:`VehicleAsset`.

    Raises:
        FileFormatError: naming ``path`` and the JSON path of the first bad field.
    """
    _require(isinstance(obj, dict), path, where, "an asset object", obj)
    _check_keys(obj, _ASSET_KEYS, _ASSET_KEYS, path, where)
    aid = obj["id"]
    _require(isinstance(aid, str) and bool(_ID_RE.match(aid)), path, f"{where}.id",
             "a lower-case id of [a-z0-9_.-] starting with a letter or digit", aid)
    file = _check_rel_file(obj["file"], path, f"{where}.file")
    cls = obj["class"]
    _require(isinstance(cls, str) and bool(_CLASS_RE.match(cls)), path, f"{where}.class",
             f"a lower-case class name such as {', '.join(VEHICLE_CLASSES[:8])}", cls)
    dims = obj["dimensions"]
    _require(isinstance(dims, list) and len(dims) == 3, path, f"{where}.dimensions",
             "[length, width, height] in metres", dims)
    for i, d in enumerate(dims):
        _require(_is_number(d) and d > 0, path, f"{where}.dimensions[{i}]", "a finite number > 0 (metres)", d)
    iss = obj["in_shape_space"]
    _require(isinstance(iss, bool), path, f"{where}.in_shape_space", "true or false", iss)
    tri = obj["triangle_count"]
    _require(isinstance(tri, int) and not isinstance(tri, bool) and tri > 0, path,
             f"{where}.triangle_count", "an integer > 0", tri)
    source = _check_json_object(obj["source"], path, f"{where}.source")
    for key in ("pack", "file"):
        _require(isinstance(source.get(key), str) and source.get(key) != "", path, f"{where}.source.{key}",
                 "a non-empty string", source.get(key))
    licence = _check_json_object(obj["licence"], path, f"{where}.licence")
    _require(isinstance(licence.get("name"), str) and licence.get("name") != "", path,
             f"{where}.licence.name", "a licence name such as \"CC0-1.0\"", licence.get("name"))
    _check_rel_file(licence.get("file"), path, f"{where}.licence.file")
    curation = _check_json_object(obj["curation"], path, f"{where}.curation")
    cleaning = _check_json_object(obj["cleaning"], path, f"{where}.cleaning")
    return VehicleAsset(
        id=aid, file=file, vehicle_class=cls,
        dimensions=(float(dims[0]), float(dims[1]), float(dims[2])),
        source=copy.deepcopy(source), licence=copy.deepcopy(licence), triangle_count=int(tri),
        cleaning=copy.deepcopy(cleaning), curation=copy.deepcopy(curation), in_shape_space=iss,
    )


def library_from_json(doc: Any, root: Path, path: Path | None = None) -> VehicleLibrary:
    """Validate a parsed library.json document and build the :class:`VehicleLibrary`."""
    check_header(doc, path, FORMAT, (VERSION,))
    _check_keys(doc, ("format", "version", "assets", "excluded"), ("assets",), path, "$")
    raw_assets = doc["assets"]
    _require(isinstance(raw_assets, list), path, "$.assets", "a list of asset objects", raw_assets)
    assets: list[VehicleAsset] = []
    seen: set[str] = set()
    for i, obj in enumerate(raw_assets):
        asset = asset_from_json(obj, path, f"$.assets[{i}]")
        _require(asset.id not in seen, path, f"$.assets[{i}].id", "an id not used by an earlier asset", asset.id)
        seen.add(asset.id)
        assets.append(asset)
    excluded = doc.get("excluded", [])
    _require(isinstance(excluded, list), path, "$.excluded", "a list of {pack, file, reason}", excluded)
    for i, ex in enumerate(excluded):
        where = f"$.excluded[{i}]"
        _require(isinstance(ex, dict), path, where, "an object {pack, file, reason}", ex)
        _check_keys(ex, _EXCLUDED_KEYS, _EXCLUDED_KEYS, path, where)
        for key in _EXCLUDED_KEYS:
            _require(isinstance(ex[key], str) and ex[key] != "", path, f"{where}.{key}", "a non-empty string", ex[key])
    return VehicleLibrary(root=Path(root), assets=assets, excluded=copy.deepcopy(excluded))


def load_library(path: str | Path = DEFAULT_LIBRARY) -> VehicleLibrary:
    """Load and validate a library.json (does not open the meshes; see ``adv3d assets check``).

    Raises:
        FileFormatError: the file is missing, not JSON, or a field breaks the contract; the
            message names the file and the JSON path.
    """
    path = Path(path)
    doc = read_json(path)
    return library_from_json(doc, path.parent, path)


def save_library(library: VehicleLibrary, path: str | Path | None = None) -> Path:
    """Write the library atomically (validated first, so a bad library never reaches disk).

    Args:
        library: the library; asset files are relative to ``path``'s folder.
        path: target file; defaults to ``library.root / "library.json"``.
    """
    path = Path(path) if path is not None else Path(library.root) / "library.json"
    doc = library.to_json()
    library_from_json(doc, path.parent, path)  # refuse to write what we could not read back
    write_json(path, doc)
    return path


def load_asset_mesh(library: VehicleLibrary, asset_id: str):
    """The asset's mesh in the convention frame (metres, +x front, z up, origin on the ground).

    Returns:
        ``trimesh.Trimesh`` with float64 vertices (n, 3) and faces (m, 3).

    Raises:
        KeyError: unknown asset id.
        MeshImportError: the file is missing or unreadable.
    """
    from .mesh_io import read_library_mesh  # trimesh import kept out of module import

    return read_library_mesh(library.path_of(asset_id))
