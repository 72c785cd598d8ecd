"""AC3D (``.ac``) and TORCS AC3D (``.acc``) files as one triangle mesh with face colours.

Format (AC3D's file format page, inivis.com "AC3D file format", and the TORCS loader
``grloadac.cpp`` for the ``.acc`` extension): a header ``AC3Db`` (a hex version digit may
follow), ``MATERIAL "name" rgb r g b amb ... emis ... spec ... shi n trans t`` lines, then a
tree of ``OBJECT world|poly|group|light`` blocks. An object carries optional ``name``,
``data N`` (N characters on the next line), ``texture`` (repeated in ``.acc``: multitexture),
``texrep``, ``texoff``, ``rot`` (9 numbers, a 3 x 3 matrix), ``loc`` (3 numbers), ``url``,
``crease``, ``subdiv``, ``hidden``, ``locked``, ``folded``; ``numvert N`` and N vertex lines
(``x y z``, plus a normal ``nx ny nz`` in ``.acc``); ``numsurf N`` and N surfaces
``SURF flags`` / ``mat i`` / ``refs n`` and n lines ``vertex u v`` (more ``u v`` pairs in
``.acc``); and ``kids N`` (always last), followed by its N children.

- Surface type (low 4 bits of the flags): 0 polygon (triangulated as a fan: AC3D polygons are
  planar and convex by the format's contract), 1 closed line and 2 line (no faces), 4 triangle
  strip (``.acc``: TORCS's ``accc`` tool writes strips; consecutive triangles alternate winding
  and are put back to one winding here). Bits 0x10 (smooth shading) and 0x20 (two-sided) do not
  change the geometry.
- Transforms: a child's vertices are in its parent's frame: ``p_parent = p @ rot + loc`` (the
  row-vector convention of plib's ``ssgLoadAC``, which TORCS uses; the identity ``rot`` of every
  TORCS car makes the order moot there).
- Colours: each face gets its material's ``rgb`` (and ``1 - trans`` as alpha); textures are not
  read (TORCS's SGI ``.rgb`` textures carry the paint of many cars, so their colour is mostly
  the material's white).
- Axes: AC3D itself is y-up (``.ac``); TORCS cars (``.acc``) are in TORCS's car frame, x forward,
  y left, z up. ``mesh_io.NATIVE_UP`` records this.
"""
from __future__ import annotations

import shlex
from pathlib import Path

import numpy as np

from ..errors import MeshImportError

#: Surface types (low nibble of ``SURF`` flags) that carry faces.
POLYGON, CLOSED_LINE, LINE, TRIANGLE_STRIP = 0, 1, 2, 4
#: Object lines that take no part in the geometry (skipped with their arguments).
_IGNORED = {"texture", "texrep", "texoff", "url", "crease", "subdiv", "hidden", "locked", "folded", "shader"}


class _Lines:
    """Line reader with the file's name and line numbers for errors."""

    def __init__(self, path: Path, text: str):
        self.path = path
        self.lines = text.splitlines()
        self.i = 0

    def next(self, what: str) -> str:
        while self.i < len(self.lines):
            line = self.lines[self.i].strip()
            self.i += 1
            if line:
                return line
        raise MeshImportError(f"{self.path}: the file ends where {what} was expected (line {self.i})")

    def next_or_none(self) -> str | None:
        """The next non-empty line, or None at the end of the file."""
        while self.i < len(self.lines):
            line = self.lines[self.i].strip()
            self.i += 1
            if line:
                return line
        return None

    def raw_next(self) -> str:
        """The next line as it is (``data`` blocks may hold anything)."""
        line = self.lines[self.i] if self.i < len(self.lines) else ""
        self.i += 1
        return line

    def fail(self, expected: str, got: str) -> MeshImportError:
        return MeshImportError(f"{self.path}: line {self.i}: expected {expected} (got {got[:80]!r})")


def _numbers(lines: _Lines, line: str, n: int, what: str, start: int = 1) -> list[float]:
    parts = line.split()
    try:
        vals = [float(x) for x in parts[start:start + n]]
    except ValueError:
        raise lines.fail(what, line) from None
    if len(vals) != n or not np.all(np.isfinite(vals)):
        raise lines.fail(what, line)
    return vals


def _count(lines: _Lines, line: str, keyword: str) -> int:
    parts = line.split()
    if len(parts) != 2 or parts[0] != keyword or not parts[1].isdigit():
        raise lines.fail(f"'{keyword} N'", line)
    return int(parts[1])


def _read_material(lines: _Lines, line: str) -> tuple[int, int, int, int]:
    try:
        tok = shlex.split(line)
    except ValueError:
        raise lines.fail('MATERIAL "name" rgb r g b ...', line) from None
    rgb, alpha = (0.7, 0.7, 0.7), 1.0
    if "rgb" in tok:
        k = tok.index("rgb")
        rgb = tuple(_numbers(lines, " ".join(tok[k:k + 4]), 3, "MATERIAL ... rgb r g b"))
    if "trans" in tok:
        k = tok.index("trans")
        alpha = 1.0 - _numbers(lines, " ".join(tok[k:k + 2]), 1, "MATERIAL ... trans t")[0]
    c = np.clip(np.array([*rgb, alpha]), 0.0, 1.0)
    return tuple(int(round(x * 255)) for x in c)  # type: ignore[return-value]


def _surface_triangles(refs: list[int], kind: int) -> list[tuple[int, int, int]]:
    if kind == POLYGON:
        return [(refs[0], refs[k], refs[k + 1]) for k in range(1, len(refs) - 1)]
    if kind == TRIANGLE_STRIP:
        out = []
        for k in range(len(refs) - 2):
            a, b, c = refs[k], refs[k + 1], refs[k + 2]
            out.append((a, b, c) if k % 2 == 0 else (b, a, c))
        return out
    return []  # lines


def _read_object(lines: _Lines, header: str, parent: np.ndarray, out: dict, depth: int) -> None:
    """Read one OBJECT block (and its children) into ``out``; ``parent``: (4, 4) row-vector
    transform of the parent frame to the file frame."""
    if depth > 256:
        raise lines.fail("objects nested at most 256 deep", header)
    rot = np.eye(3)
    loc = np.zeros(3)
    verts = np.zeros((0, 3))
    faces: list[tuple[int, int, int]] = []
    mats: list[int] = []
    while True:
        line = lines.next("an object field or 'kids N'")
        key = line.split()[0]
        if key == "kids":
            n_kids = _count(lines, line, "kids")
            break
        if key == "name":
            continue
        if key == "data":
            n = _count(lines, line, "data")
            got = 0
            while got < n and lines.i < len(lines.lines):
                got += len(lines.raw_next()) + 1
            continue
        if key == "rot":
            rot = np.array(_numbers(lines, line, 9, "'rot' and 9 numbers")).reshape(3, 3)
        elif key == "loc":
            loc = np.array(_numbers(lines, line, 3, "'loc x y z'"))
        elif key == "numvert":
            n = _count(lines, line, "numvert")
            verts = np.array([_numbers(lines, lines.next("a vertex line"), 3, "a vertex 'x y z'", start=0)
                              for _ in range(n)]).reshape(n, 3)
        elif key == "numsurf":
            n = _count(lines, line, "numsurf")
            for _ in range(n):
                faces_s, mat = _read_surface(lines, len(verts))
                faces += faces_s
                mats += [mat] * len(faces_s)
        elif key in _IGNORED:
            continue
        else:
            raise lines.fail("an AC3D object field (name, data, texture, rot, loc, numvert, numsurf, kids, ...)",
                             line)
    local = np.eye(4)
    local[:3, :3] = rot
    local[3, :3] = loc
    world = local @ parent  # row vectors: p_file = [p, 1] @ local @ parent
    if faces:
        p = np.c_[verts, np.ones(len(verts))] @ world
        out["vertices"].append(p[:, :3])
        out["faces"].append(np.asarray(faces, dtype=np.int64) + out["n"])
        out["materials"].append(np.asarray(mats, dtype=np.int64))
        out["n"] += len(verts)
    for _ in range(n_kids):
        child = lines.next("a child 'OBJECT type'")
        if not child.startswith("OBJECT"):
            raise lines.fail("'OBJECT type' (a child of the object above)", child)
        _read_object(lines, child, world, out, depth + 1)


def _read_surface(lines: _Lines, n_verts: int) -> tuple[list[tuple[int, int, int]], int]:
    line = lines.next("'SURF flags'")
    parts = line.split()
    if len(parts) != 2 or parts[0] != "SURF":
        raise lines.fail("'SURF flags'", line)
    try:
        flags = int(parts[1], 0)
    except ValueError:
        raise lines.fail("'SURF 0x..' (hexadecimal flags)", line) from None
    mat = 0
    line = lines.next("'mat i' or 'refs n'")
    if line.split()[0] == "mat":
        mat = _count(lines, line, "mat")
        line = lines.next("'refs n'")
    n = _count(lines, line, "refs")
    refs = []
    for _ in range(n):
        ref_line = lines.next("a surface vertex 'index u v'")
        tok = ref_line.split()
        if not tok or not tok[0].isdigit() or int(tok[0]) >= n_verts:
            raise lines.fail(f"a vertex index in [0, {n_verts})", ref_line)
        refs.append(int(tok[0]))
    kind = flags & 0x0F
    if kind not in (POLYGON, CLOSED_LINE, LINE, TRIANGLE_STRIP):
        raise lines.fail("a surface type 0 (polygon), 1 or 2 (lines) or 4 (triangle strip)", f"SURF {parts[1]}")
    return _surface_triangles(refs, kind), mat


def read_ac3d(path: str | Path):
    """Read an AC3D ``.ac`` or TORCS ``.acc`` file as one mesh in its file frame.

    Returns:
        ``trimesh.Trimesh`` (float64 vertices; one RGBA colour per face from its material;
        degenerate strip triangles left out); ``metadata["ac3d_objects"]``: objects with faces.
    Raises:
        MeshImportError: not AC3D, or a line breaks the format (names the file and line).
    """
    import trimesh

    path = Path(path)
    try:
        text = path.read_text(encoding="latin-1")
    except OSError as exc:
        raise MeshImportError(f"{path}: cannot read ({exc.strerror})") from None
    lines = _Lines(path, text)
    head = lines.next("the 'AC3Db' header")
    if not head.startswith("AC3D"):
        raise lines.fail("the header 'AC3Db' (an AC3D file)", head)
    materials: list[tuple[int, int, int, int]] = []
    out = {"vertices": [], "faces": [], "materials": [], "n": 0}
    objects = 0
    while True:
        line = lines.next_or_none()
        if line is None:
            break
        if line.startswith("MATERIAL"):
            materials.append(_read_material(lines, line))
        elif line.startswith("OBJECT"):
            _read_object(lines, line, np.eye(4), out, 0)
            objects += 1
        else:
            raise lines.fail("'MATERIAL ...' or 'OBJECT type'", line)
    if not out["faces"]:
        raise MeshImportError(f"{path}: the file holds no polygons")
    v = np.vstack(out["vertices"])
    f = np.vstack(out["faces"])
    mat = np.concatenate(out["materials"])
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f, mat = f[keep], mat[keep]
    palette = np.array(materials or [(180, 180, 180, 255)], dtype=np.uint8)
    if mat.size and mat.max() >= len(palette):
        raise MeshImportError(f"{path}: a surface uses material {int(mat.max())} but the file defines "
                              f"{len(materials)}")
    mesh = trimesh.Trimesh(v, f, face_colors=palette[mat], process=False)
    mesh.metadata["ac3d_objects"] = len(out["faces"])
    return mesh
