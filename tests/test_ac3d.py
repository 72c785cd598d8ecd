"""AC3D / TORCS .acc reader (adv3d_runner/shapes/ac3d.py) on a hand-written file, and the
TORCS cars of Debian's torcs-data when they are unpacked on this machine."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.errors import MeshImportError
from adv3d_runner.shapes.ac3d import read_ac3d
from adv3d_runner.shapes.mesh_io import import_vehicle, read_mesh

DATA = Path(__file__).parent / "data" / "ac3d_box_car.acc"
TORCS_CARS = Path(os.environ.get("ADV3D_TORCS_CARS", "/tmp/torcs/x/usr/share/games/torcs/cars"))


def test_hand_written_acc_reads_polygons_strips_materials_and_offsets():
    mesh, info = read_mesh(DATA)
    assert info == {"format": ".acc", "native_up": "+y", "reader": "ac3d"}
    # body: 4 quads (8 triangles) + a 4-vertex strip (2) + a line (none); cabin: 5 quads (10)
    assert len(mesh.faces) == 20
    colours = np.asarray(mesh.visual.face_colors)
    assert (colours[:10] == [255, 0, 0, 255]).all()
    assert (colours[10:] == [0, 0, 255, 128]).all()  # trans 0.5 -> alpha 128
    # loc moves the body up by 0.5 and the cabin by 1.0 (y up)
    assert np.allclose(mesh.bounds, [[-2, 0, -0.9], [2, 1.5, 0.9]])
    # the strip's two triangles (faces 8, 9: the -x end cap) are wound the same way
    n = mesh.face_normals[8:10]
    assert np.allclose(n[0], n[1])
    assert abs(n[0][0]) == pytest.approx(1.0)


def test_acc_imports_upright_in_the_convention():
    mesh, curation, _ = import_vehicle(DATA)
    assert curation["reader"] == "ac3d"
    assert curation["up"].startswith("+y")
    assert np.allclose(mesh.extents, [4.0, 1.8, 1.5])
    assert mesh.vertices[:, 2].min() == pytest.approx(0.0)


def test_rot_is_applied_to_vertices_and_children(tmp_path):
    text = DATA.read_text().replace('name "cabin"\nloc 0 1 0', 'name "cabin"\nrot 0 1 0 -1 0 0 0 0 1\nloc 0 1 0')
    p = tmp_path / "rot.ac"
    p.write_text(text)
    mesh = read_ac3d(p)
    cabin = mesh.vertices[np.unique(mesh.faces[10:])]
    # rows-as-given, row vectors: (x, y, z) -> (-y, x, z): the 2 m x 0.5 m cabin stands up
    assert np.allclose(np.ptp(cabin, axis=0), [0.5, 2.0, 1.6])


@pytest.mark.parametrize("edit, message", [
    (lambda t: "AC3X\n" + t.split("\n", 1)[1], "line 1: expected the header 'AC3Db'"),
    (lambda t: t.replace("refs 4\n0 0 0\n1 1 0", "refs 4\n0 0 0\n9 1 0", 1), "a vertex index in [0, 8)"),
    (lambda t: t.replace("numvert 8\n-2 -0.5", "numvert 8\n-2 nan", 1), "a vertex 'x y z'"),
    (lambda t: t.replace("SURF 0x10", "SURF 0x13", 1), "a surface type 0"),
    (lambda t: t.replace("mat 1", "mat 7"), "uses material 7"),
    (lambda t: t.rsplit("kids 0", 1)[0], "the file ends"),
    (lambda t: t.replace("numsurf 6", "bogus 6"), "an AC3D object field"),
])
def test_broken_files_name_file_line_and_field(tmp_path, edit, message):
    p = tmp_path / "bad.acc"
    p.write_text(edit(DATA.read_text()))
    with pytest.raises(MeshImportError) as err:
        read_mesh(p)
    assert str(p) in str(err.value)
    assert message in str(err.value)


@pytest.mark.skipif(not (TORCS_CARS / "p406" / "p406.acc").is_file(),
                    reason="TORCS cars not unpacked (apt-get download torcs-data; dpkg-deb -x; ADV3D_TORCS_CARS)")
def test_torcs_p406_imports_at_its_body_size():
    mesh, curation, _ = import_vehicle(TORCS_CARS / "p406" / "p406.acc")
    # p406.xml: body length 4.64 m, width 2.0 m, height 1.27 m
    assert np.allclose(mesh.extents, [4.64, 2.0, 1.27], atol=0.01)
