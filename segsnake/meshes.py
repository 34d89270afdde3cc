"""The snake's surface as files in world coordinates: ``surface.vtp`` and an optional STL/OBJ/PLY.

Both hold the model's default sampling (8 vertices per control interval, poles or end caps closed)
with the image affine applied, so they overlay the image in any viewer (ParaView, 3D Slicer,
MeshLab, a slicer for 3D printing). Importing this module is light: VTK and pyvista load on use.
"""

from __future__ import annotations

import numpy as np

__all__ = ["MESH_SUFFIXES", "mesh_suffix", "world_mesh", "write_surface", "write_mesh"]

# What ``--mesh NAME`` accepts: formats pyvista writes and every mesh viewer opens.
MESH_SUFFIXES = (".stl", ".obj", ".ply")


def mesh_suffix(name: str) -> str | None:
    """The mesh format of ``name`` (``".stl"``, ``".obj"``, ``".ply"``; any case), or None."""
    low = name.lower()
    return next((s for s in MESH_SUFFIXES if low.endswith(s) and len(low) > len(s)), None)


def world_mesh(model, volume):
    """The model's triangle mesh (``pyvista.PolyData``) with float32 world-mm points.

    Parameters
    ----------
    model : SplineSurface
        The snake, in mm of scaled index space.
    volume : Volume
        The image: its spacing and affine map the model to world coordinates.
    """
    mesh = model.to_mesh()
    index = np.asarray(mesh.points, dtype=np.float64) / np.asarray(volume.spacing)
    mesh.points = volume.index_to_world(index).astype(np.float32)
    return mesh


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

    mesh = world_mesh(model, volume)
    writer = vtkXMLPolyDataWriter()
    writer.SetInputData(mesh)
    writer.SetWriteToOutputString(True)
    # Inline binary is base64 text, so the string is plain ASCII (appended raw data would not
    # survive the str round trip of the Python wrapper).
    writer.SetDataModeToBinary()
    writer.SetCompressorTypeToZLib()
    if writer.Write() != 1:
        raise OSError(f"VTK could not serialise the surface ({mesh.n_points} points)")
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
