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
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..errors import ConfigError, MeshImportError, UnknownIdError
from ..fileio import REPO_ROOT, atomic_path, resolve_inside, write_json
from ..validate import Node, check_header
from ..vehicle_classes import CLASS_PATTERN, class_examples, is_class_name

FORMAT = "adv3d-vehicle-library"
VERSION = 1
DEFAULT_LIBRARY: Path = REPO_ROOT / "assets" / "vehicles" / "library.json"

#: An asset id: it names the mesh file, so at most 128 characters, as every name of a file.
_ID_RE = re.compile(r"^[a-z0-9][a-z0-9_.-]{0,127}$")
ID_EXPECTED = "a lower-case id of [a-z0-9_.-] starting with a letter or digit, at most 128 characters"
_ASSET_KEYS = ("id", "file", "class", "dimensions", "in_shape_space", "triangle_count",
               "source", "licence", "curation", "cleaning")
_EXCLUDED_KEYS = ("pack", "file", "reason")
#: Licence text files looked for beside an imported mesh, in this order.
LICENCE_NAMES = ("License.txt", "LICENSE.txt", "LICENSE", "Licence.txt", "LICENCE", "license.txt")


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
        """The asset with this id; ``UnknownIdError`` (a ``KeyError``) listing the known ids if
        absent."""
        for asset in self.assets:
            if asset.id == asset_id:
                return asset
        raise UnknownIdError(f"no asset {asset_id!r} in the library at {self.root} "
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
        """Path of an asset's mesh file, checked to stay inside the library folder (symlinks
        included; ``FileFormatError`` naming library.json and the asset's ``file`` field)."""
        if isinstance(asset, str):
            asset = self.get(asset)
        index = next((i for i, a in enumerate(self.assets) if a.id == asset.id), None)
        return resolve_inside(self.root, asset.file, file=self.root / "library.json", field=f"$.assets[{index}].file",
                              inside="the library folder")

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

def asset_from_json(obj: Any, path: Path | None = None, where: str = "$") -> VehicleAsset:
    """Validate one asset object and build the :class:`VehicleAsset`.

    Raises:
        FileFormatError: naming ``path`` and the JSON path of the first bad field.
    """
    return _asset(obj if isinstance(obj, Node) else Node(obj, where, path))


def _asset(node: Node) -> VehicleAsset:
    node.object("an asset object")
    node.check_keys(_ASSET_KEYS, required=_ASSET_KEYS)
    aid = node["id"].string(pattern=_ID_RE, expected=ID_EXPECTED)
    file = node["file"].rel_path(inside="the library folder")
    cls = node["class"].string(pattern=CLASS_PATTERN,
                               expected=f"a lower-case class name such as {', '.join(class_examples(8))}")
    dims = node["dimensions"].numbers(length=3, lo=0.0, lo_open=True, expected="a finite number > 0 (metres)")
    iss = node["in_shape_space"].boolean()
    tri = node["triangle_count"].integer(lo=1, expected="an integer > 0")
    source = node["source"]
    source.object("a JSON object")
    for key in ("pack", "file"):
        source.get(key).string()
    licence = node["licence"]
    licence.object("a JSON object")
    licence.get("name").string(expected='a licence name such as "CC0-1.0"')
    licence.get("file").rel_path(inside="the library folder")
    curation = node["curation"].object("a JSON object")
    cleaning = node["cleaning"].object("a JSON object")
    return VehicleAsset(
        id=aid, file=file, vehicle_class=cls,
        dimensions=(float(dims[0]), float(dims[1]), float(dims[2])),
        source=copy.deepcopy(source.value), licence=copy.deepcopy(licence.value), triangle_count=tri,
        cleaning=copy.deepcopy(cleaning), curation=copy.deepcopy(curation), in_shape_space=iss,
    )


def library_from_json(doc: Any, root: Path, path: Path | None = None) -> VehicleLibrary:
    """Validate a parsed library.json document and build the :class:`VehicleLibrary`."""
    node = doc if isinstance(doc, Node) else Node(doc, "$", path)
    check_header(node, FORMAT, (VERSION,))
    node.check_keys(("format", "version", "assets", "excluded"), required=("assets",))
    assets: list[VehicleAsset] = []
    seen: set[str] = set()
    for item in node["assets"].items("a list of asset objects"):
        asset = _asset(item)
        item["id"].unique(asset.id, seen, "asset id")
        assets.append(asset)
    excluded = node.get("excluded", [])
    for ex in excluded.objects("a list of {pack, file, reason}", item="an object {pack, file, reason}"):
        ex.check_keys(_EXCLUDED_KEYS, required=_EXCLUDED_KEYS)
        for key in _EXCLUDED_KEYS:
            ex[key].string()
    return VehicleLibrary(root=Path(root), assets=assets, excluded=copy.deepcopy(excluded.value))


def load_library(path: str | Path = DEFAULT_LIBRARY) -> VehicleLibrary:
    """Load and validate a library.json (does not open the meshes; see ``adv3d assets check``).

    Raises:
        FileFormatError: the file is missing, not JSON, or a field breaks the contract; the
            message names the file and the JSON path.
    """
    path = Path(path)
    return library_from_json(Node.load(path), path.parent, path)


def library_fingerprint(library: VehicleLibrary) -> str:
    """``sha256:`` over the library's records and the bytes of every mesh file it lists.

    What a scene's actors look like depends on both; runs record it (run.json) and a resume
    refuses another library. Missing mesh files count as empty.
    """
    import hashlib
    import json

    h = hashlib.sha256(json.dumps(library.to_json(), sort_keys=True).encode())
    for asset in library.assets:
        path = library.path_of(asset)
        h.update(asset.file.encode() + b"\0")
        h.update(hashlib.sha256(path.read_bytes() if path.is_file() else b"").digest())
    return "sha256:" + h.hexdigest()


def resolve_library(arg: str | Path | None) -> VehicleLibrary | None:
    """The library a ``--library`` option names: None or "" -> the bundled one, ``"none"`` ->
    None (actors are boxes), else that library.json."""
    if arg is None or str(arg) == "":
        return load_library(DEFAULT_LIBRARY)
    if str(arg).lower() == "none":
        return None
    return load_library(Path(arg))


def load_or_new_library(path: str | Path) -> VehicleLibrary:
    """The library at ``path``, or a new empty one rooted in its folder if there is no file."""
    path = Path(path)
    return load_library(path) if path.exists() else VehicleLibrary(root=path.parent)


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


# ----------------------------------------------------------------------------- adding assets

#: ``read(path) -> (mesh in the convention frame, curation record, cleaning report)``: how a
#: vehicle file becomes a mesh (``mesh_io.import_vehicle`` for the CLI, Blender's importers
#: followed by ``mesh_io.convert_vehicle`` in the add-on).
MeshReader = Callable[[Path], tuple[Any, dict, dict]]


def slug(text: str) -> str:
    """File-name-safe lower-case id part: ``"SportsCar2"`` -> ``"sportscar2"``."""
    s = re.sub(r"[^a-z0-9._-]+", "-", text.lower()).strip("-.")
    if not s:
        raise ConfigError(f"cannot make an id from {text!r}; give an asset id")
    return s


def find_licence(folder: Path) -> Path | None:
    """The licence text beside a source file (one of :data:`LICENCE_NAMES`), or None."""
    for name in LICENCE_NAMES:
        if (folder / name).is_file():
            return folder / name
    return None


def licence_name_from_text(text: str) -> str | None:
    """The SPDX name of a licence text we can recognise (CC0, CC-BY 4.0), or None."""
    t = text.lower()
    if "cc0" in t or "creative commons zero" in t or "publicdomain/zero" in t:
        return "CC0-1.0"
    if "creativecommons.org/licenses/by/4.0" in t:
        return "CC-BY-4.0"
    return None


def add_asset(library: VehicleLibrary, library_path: str | Path, source: str | Path, vehicle_class: str,
              read: MeshReader, *, asset_id: str | None = None, pack: str | None = None,
              licence_file: str | Path | None = None, licence_name: str | None = None, author: str = "",
              url: str = "", note: str = "", in_shape_space: bool = True, replace: bool = True) -> VehicleAsset:
    """Add one vehicle file to ``library`` (or replace the asset with the same id) and save it.

    The one import pipeline behind ``adv3d assets import`` and the add-on's *Import vehicle*:
    everything that can be refused (class, file, licence) is checked before the mesh is read;
    the mesh is written to ``<pack>/<name>.glb`` beside ``library_path``; dimensions and
    triangle count come from the stored file (float32 in glb); the licence text is copied to
    ``<pack>/``; the library is saved atomically (after each asset, so a failure later keeps
    earlier work).

    Args:
        library: the library to add to (modified in place; its ``root`` is the mesh folder).
        library_path: where to save it (``library.json``).
        source: the vehicle file.
        vehicle_class: a lower-case class name (``adv3d_runner.vehicle_classes``).
        read: turns ``source`` into (mesh, curation record, cleaning report); see
            :data:`MeshReader`.
        asset_id: default ``<pack>.<file stem>`` (slugged).
        pack: source pack folder name; default the source file's folder name.
        licence_file: licence text; default one of :data:`LICENCE_NAMES` beside ``source``.
        licence_name: SPDX name; default read from the licence text. Named without a licence
            text anywhere, a note naming the licence and the source file is stored as the
            asset's licence file (``<pack>/LICENCE-<name>.txt``).
        replace: replace an asset with the same id (False: refuse it).
        author, url: credited in the ``source`` record.
        note: why the asset was curated this way (``curation.note``).
        in_shape_space: include the asset in the PCA shape space.

    Returns:
        the stored :class:`VehicleAsset`.

    Raises:
        ConfigError: bad class or id, no licence file, unknown licence. MeshImportError: the
            file is missing or cannot be read as a mesh. FileFormatError: the library would
            not validate (nothing is written then).
    """
    from .mesh_io import mesh_dimensions, read_library_mesh, write_library_glb

    source = Path(source)
    if not is_class_name(vehicle_class):
        raise ConfigError(f"the class must be a lower-case name such as sedan or suv (got {vehicle_class!r})")
    if not source.is_file():
        raise MeshImportError(f"{source}: no such file")
    pack = slug(pack or source.parent.name)
    if not _ID_RE.match(pack):  # the pack is a folder of the library
        raise ConfigError(f"source pack {pack!r}: expected {ID_EXPECTED}; give a shorter --source-pack")
    asset_id = asset_id or f"{pack}.{slug(source.stem)}"
    if not _ID_RE.match(asset_id):
        raise ConfigError(f"asset id {asset_id!r}: expected {ID_EXPECTED}")
    if not replace and asset_id in library.ids():
        raise ConfigError(f"asset id {asset_id!r} is already in the library; replace it explicitly or give "
                          "another id")
    licence_src = Path(licence_file) if licence_file else find_licence(source.parent)
    licence_note = None
    if licence_file and not licence_src.is_file():
        raise ConfigError(f"{licence_src}: no such licence file")
    if licence_src is None:
        if not licence_name:
            raise ConfigError(f"{source}: no licence file beside it; give the licence file or name the licence "
                              "(licences travel with meshes)")
        if not re.fullmatch(r"[A-Za-z0-9.+-]{1,64}", licence_name):
            raise ConfigError(f"licence name {licence_name!r}: expected an SPDX identifier such as CC0-1.0")
        licence_note = (f"{source.name} (source pack {pack}) is used under the licence {licence_name} (SPDX),\n"
                        f"as named when it was imported; no licence text was beside the file.\n"
                        f"https://spdx.org/licenses/{licence_name}.html\n")
    licence_name = licence_name or licence_name_from_text(licence_src.read_text(errors="replace"))
    if not licence_name:
        raise ConfigError(f"{licence_src}: cannot tell the licence from its text; give its name (e.g. CC0-1.0)")

    mesh, curation, report = read(source)
    if len(getattr(mesh, "faces", ())) == 0:
        raise MeshImportError(f"{source}: no triangles left after conversion and cleaning; nothing was changed")
    rel_file = f"{pack}/{asset_id.split('.', 1)[-1] if asset_id.startswith(pack + '.') else asset_id}.glb"
    target = resolve_inside(library.root, rel_file, field="asset file", inside="the library folder")
    lic_rel = f"{pack}/{licence_src.name}" if licence_src is not None else f"{pack}/LICENCE-{licence_name}.txt"
    if note:
        curation["note"] = note
    # Nothing the library had is touched until the new mesh has been written beside it, read
    # back and the new library validated: a broken mesh under an existing id keeps the old one.
    with atomic_path(target) as tmp:
        write_library_glb(mesh, tmp)
        try:
            stored = read_library_mesh(tmp)  # dimensions from what is on disk (float32 in glb)
        except MeshImportError as exc:
            raise MeshImportError(f"{source}: the converted mesh cannot be read back ({exc}); "
                                  "nothing was changed in the library") from None
        asset = VehicleAsset(
            id=asset_id, file=rel_file, vehicle_class=vehicle_class,
            dimensions=tuple(round(v, 4) for v in mesh_dimensions(stored)),
            source={"pack": pack, "file": source.name, "author": author, "url": url},
            licence={"name": licence_name, "file": lic_rel},
            triangle_count=int(len(stored.faces)), cleaning=report, curation=curation,
            in_shape_space=in_shape_space,
        )
        trial = VehicleLibrary(root=library.root, assets=list(library.assets), excluded=library.excluded)
        trial.put(asset)
        library_from_json(trial.to_json(), Path(library_path).parent, Path(library_path))
    if licence_note is not None:
        (library.root / pack).mkdir(parents=True, exist_ok=True)
        (library.root / lic_rel).write_text(licence_note)
    elif (library.root / lic_rel).resolve() != licence_src.resolve():
        (library.root / pack).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(licence_src, library.root / lic_rel)
    library.put(asset)
    save_library(library, library_path)
    return asset
