"""The snake's surface as files in world coordinates: ``surface.vtp`` and an optional STL/OBJ/PLY.

Both hold the model's default sampling (8 vertices per control interval, poles or end caps closed)
with the image affine applied, so they overlay the image in any viewer (ParaView, 3D Slicer,
MeshLab, a slicer for 3D printing). Importing this module is light: VTK loads on use, and pyvista
only for the STL/OBJ/PLY file (``surface.vtp`` is built with VTK's own classes, the same file byte
for byte: importing pyvista took 0.14 s of every ``segment`` run for a wrapper it does not need).
"""

from __future__ import annotations

import numpy as np

__all__ = ["MESH_SUFFIXES", "mesh_suffix", "world_triangles", "world_mesh", "write_surface",
           "write_mesh"]

# What ``--mesh NAME`` accepts: formats pyvista writes and every mesh viewer opens.
MESH_SUFFIXES = (".stl", ".obj", ".ply")


def mesh_suffix(name: str) -> str | None:
    """The mesh format of ``name`` (``".stl"``, ``".obj"``, ``".ply"``; any case), or None."""
    low = name.lower()
    return next((s for s in MESH_SUFFIXES if low.endswith(s) and len(low) > len(s)), None)


def world_triangles(model, volume) -> tuple[np.ndarray, np.ndarray]:
    """The model's default triangle mesh (:meth:`SplineSurface.triangles`) in world mm: float32
    points ``(n, 3)`` and int64 outward-oriented triangles ``(f, 3)``.

    Parameters
    ----------
    model : SplineSurface
        The snake, in mm of scaled index space.
    volume : Volume
        The image: its spacing and affine map the model to world coordinates.
    """
    points, tris = model.triangles()
    return _world_points(points, volume), _world_order(np.asarray(tris, dtype=np.int64), volume)


def world_mesh(model, volume):
    """The model's triangle mesh (``pyvista.PolyData``, :meth:`SplineSurface.to_mesh`) with the
    float32 world-mm points of :func:`world_triangles` (same parameters)."""
    mesh = model.to_mesh()
    mesh.points = _world_points(mesh.points, volume)
    faces = np.asarray(mesh.faces).reshape(-1, 4)  # (3, a, b, c) a triangle
    tris = faces[:, 1:]
    reordered = _world_order(tris, volume)
    if reordered is not tris:
        mesh.faces = np.column_stack([faces[:, 0], reordered]).ravel()
    return mesh


def _world_order(tris: np.ndarray, volume) -> np.ndarray:
    """Triangles outward in world mm: where the affine mirrors (a negative determinant: a LAS
    grid, for one), the index space's outward triangles turn inward and are reversed (a new
    array); otherwise ``tris`` itself."""
    if np.linalg.det(np.asarray(volume.affine, dtype=np.float64)[:3, :3]) < 0:
        return tris[:, ::-1].copy()
    return tris


def _world_points(points: np.ndarray, volume) -> np.ndarray:
    """Points in mm of the volume's scaled index space as float32 world mm."""
    index = np.asarray(points, dtype=np.float64) / np.asarray(volume.spacing)
    return volume.index_to_world(index).astype(np.float32)


def _vtk_polydata(points: np.ndarray, tris: np.ndarray):
    """A ``vtkPolyData`` of float32 ``points`` and triangles ``tris`` (int64), deep copies: the
    same arrays pyvista's ``PolyData`` holds (float32 points, 64-bit offsets and connectivity),
    so ``surface.vtp`` is byte for byte the file written through pyvista before."""
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float32), deep=True))
    offsets = np.arange(0, 3 * len(tris) + 1, 3, dtype=np.int64)
    cells = vtkCellArray()
    # (plain 64-bit integer arrays, not vtkIdTypeArray, which the file would mark IdType="1")
    cells.SetData(numpy_to_vtk(offsets, deep=True),
                  numpy_to_vtk(np.ascontiguousarray(tris, dtype=np.int64).ravel(), deep=True))
    poly = vtkPolyData()
    poly.SetPoints(vtk_points)
    poly.SetPolys(cells)
    return poly


def write_surface(path: str, model, volume) -> None:
    """Write the snake as a VTK XML PolyData file (``.vtp``) in world coordinates.

    Binary, zlib-compressed. The file is serialised in memory and written with Python's I/O:
    VTK's own file output aborts the whole process on a full disk (measured: ``free(): invalid
    pointer`` with VTK 9.7), where Python raises an ``OSError`` the caller turns into a clean
    failure.

    Parameters
    ----------
    path : str
        Destination file.
    model : SplineSurface
        The snake, in mm of scaled index space.
    volume : Volume
        The image (spacing and affine).
    """
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter

    mesh = _vtk_polydata(*world_triangles(model, volume))
    writer = vtkXMLPolyDataWriter()
    writer.SetInputData(mesh)
    writer.SetWriteToOutputString(True)
    # Inline binary is base64 text, so the string is plain ASCII (appended raw data would not
    # survive the str round trip of the Python wrapper).
    writer.SetDataModeToBinary()
    writer.SetCompressorTypeToZLib()
    if writer.Write() != 1:
        raise OSError(f"VTK could not serialise the surface ({mesh.GetNumberOfPoints()} points)")
    text = writer.GetOutputString()
    with open(path, "wb") as fh:
        fh.write(text.encode("ascii"))


def write_mesh(path: str, model, volume) -> None:
    """Write the snake as STL, OBJ or PLY (by ``path``'s extension) in world coordinates.

    Written through pyvista (binary STL and PLY). Only normals-free triangles are stored: every
    viewer recomputes shading normals, and the faces are consistently outward-oriented.

    Parameters
    ----------
    path : str
        Destination file ending in ``.stl``, ``.obj`` or ``.ply``.
    model : SplineSurface
        The snake, in mm of scaled index space.
    volume : Volume
        The image (spacing and affine).

    Raises
    ------
    ValueError
        ``path`` has another extension (the options layer refuses it before any work).
    OSError
        The file could not be written or is empty afterwards.
    """
    import os

    suffix = mesh_suffix(os.path.basename(path))
    if suffix is None:
        raise ValueError(f"{path}: not a mesh file name (expected one of {MESH_SUFFIXES})")
    mesh = world_mesh(model, volume)
    # pyvista picks the writer by the lower-case extension only: "a.STL" goes through "a.STL.stl".
    target = path if path.endswith(suffix) else path + suffix
    try:
        mesh.save(target, binary=suffix != ".obj")  # OBJ is a text format only
        if target != path:
            os.replace(target, path)
    finally:
        if target != path and os.path.lexists(target):
            os.unlink(target)
    # VTK's writers report some failures only through their error log: check the result.
    if not os.path.isfile(path) or os.path.getsize(path) == 0:
        raise OSError(f"{path}: the mesh writer produced no data")
