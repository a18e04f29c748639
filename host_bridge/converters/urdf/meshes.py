"""The visuals' geometry: a URDF ``<box>``, ``<cylinder>``, ``<sphere>`` or ``<mesh>`` -> one
Rerun archetype, with the URDF material's colour.

Mesh files are read through the robot's :class:`~host_bridge.core.resources.ResourceResolver`
(``package://`` from ``--package-path``, the ROS paths or the robot's file server; ``file://``;
paths relative to the ``--urdf`` file), the files beside a mesh (OBJ .mtl, textures) through the
same resolver, and loaded by trimesh (STL, OBJ, DAE, glTF, PLY...). Mesh scale is applied to the
vertices, so positions are metres as in trimesh's own load times the scale.

Several materials in one file become per-vertex colours; trimesh would pack them into a
texture through glTF's linear colour rule, which makes a Collada or OBJ diffuse colour (written
as it should look, as RViz shows it) lighter. glTF's own base colour is linear and is turned into
sRGB, the space of Rerun's colours.

A visual that cannot be drawn (a missing or broken file, a mesh over :data:`MAX_MESH_BYTES`,
sizes that are not finite) raises MissingResourceError or ConvertError for itself alone;
:func:`missing_files` words the missing ones for the converter's one warning.
"""

from __future__ import annotations

import io
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.core.resources import ResourceResolver
from host_bridge.errors import ConvertError, MissingResourceError

if TYPE_CHECKING:
    # Imported where a model is built: trimesh (with scipy) and yourdfpy take about a second to
    # import, which every --bag run without a robot description paid.
    import trimesh
    import yourdfpy

VisualArchetype = rr.Mesh3D | rr.Boxes3D | rr.Cylinders3D | rr.Ellipsoids3D

# glTF stores its base colour linear; trimesh's other loaders keep the colour as written.
_LINEAR_COLOUR_TYPES = frozenset({"gltf", "glb"})

MAX_MESH_BYTES = 64 << 20
"""The largest mesh file loaded (64 MiB, also the relay's file server limit). That is millions
of triangles already; a bigger file (an unreduced CAD export, a corrupt file full of zeros)
would hold the robot's converting thread for seconds and cost several times its size in
memory while trimesh parses it, for one visual. It is named, with its size, and not drawn."""


def visual_geometry(
    visual: yourdfpy.Visual,
    colors: Mapping[str, Any],
    resolver: ResourceResolver,
    base: Path | None,
) -> VisualArchetype:
    geometry = visual.geometry
    color = _urdf_color(visual, colors)
    solid = rr.components.FillMode.Solid
    color_list = None if color is None else [color]
    if geometry is not None:
        if geometry.mesh is not None:
            return _mesh(geometry.mesh, color, resolver, base)
        if geometry.box is not None:
            _check_sizes("<box> size", geometry.box.size)
            half_sizes = [np.asarray(geometry.box.size, np.float64) / 2.0]
            return rr.Boxes3D(half_sizes=half_sizes, colors=color_list, fill_mode=solid)
        if geometry.cylinder is not None:
            cylinder = geometry.cylinder
            _check_sizes("<cylinder> length and radius", (cylinder.length, cylinder.radius))
            return rr.Cylinders3D(
                lengths=[cylinder.length],
                radii=[cylinder.radius],
                colors=color_list,
                fill_mode=solid,
            )
        if geometry.sphere is not None:
            radius = geometry.sphere.radius
            _check_sizes("<sphere> radius", (radius,))
            return rr.Ellipsoids3D(half_sizes=[[radius] * 3], colors=color_list, fill_mode=solid)
    msg = "the visual has no <geometry> (mesh, box, cylinder or sphere)"
    raise ConvertError(msg)


def _rgba8(rgba: Any) -> npt.NDArray[np.uint8]:
    return np.clip(np.round(np.asarray(rgba, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def _urdf_color(visual: yourdfpy.Visual, colors: Mapping[str, Any]) -> npt.NDArray[np.uint8] | None:
    material = visual.material
    if material is None:
        return None
    if material.color is not None:
        return _rgba8(material.color.rgba)
    rgba = colors.get(material.name or "")
    return None if rgba is None else _rgba8(rgba)


def _check_sizes(what: str, sizes: npt.ArrayLike) -> None:
    values = np.asarray(sizes, np.float64)
    if not (np.isfinite(values).all() and (values >= 0).all()):
        msg = f"its {what} {values.tolist()} is not finite and >= 0"
        raise ConvertError(msg)


def missing_files(missing: Sequence[tuple[str, MissingResourceError]]) -> list[str]:
    """One clause per place looked in: the files by directory with the links that name them,
    where they were looked for, and each ``--package-path`` that would help, once."""
    by_search: dict[str, dict[str, list[tuple[str, str]]]] = {}
    for visual, err in missing:
        directory, _, name = err.uri.rpartition("/")
        by_search.setdefault(err.searched, {}).setdefault(directory, []).append((name, visual))
    clauses = []
    for searched, directories in by_search.items():
        listed = []
        for directory, files in directories.items():
            if len(files) == 1:
                name, visual = files[0]
                listed.append(f"{directory}/{name} for {visual}")
            else:
                names = ", ".join(f"{name} for {visual}" for name, visual in files)
                listed.append(f"{directory}/: {names}")
        clauses.append(f"mesh files not found: {'; '.join(listed)}; looked in {searched}")
    packages = sorted({err.package for _, err in missing if err.package is not None})
    if packages:
        clauses.append("pass " + " ".join(f"--package-path {p}=DIR" for p in packages))
    return clauses


def _read_mesh(uri: str, resolver: ResourceResolver, base: Path | None) -> bytes:
    """The file's bytes, unless it is over :data:`MAX_MESH_BYTES` (a local file is measured
    before it is read)."""
    path = resolver.locate(uri, base)
    size = path.stat().st_size if path is not None else None
    data = None
    if size is None or size <= MAX_MESH_BYTES:
        data = resolver.read(uri, base)
        size = len(data)
    if data is None or size > MAX_MESH_BYTES:
        msg = (
            f"{uri}: {size} bytes ({size / (1 << 20):.0f} MiB) is over the mesh size limit of "
            f"{MAX_MESH_BYTES >> 20} MiB (urdf.meshes.MAX_MESH_BYTES), not loaded; reduce the mesh "
            "(MeshLab, Blender's Decimate)"
        )
        raise ConvertError(msg)
    return data


class _SiblingFiles(Mapping[str, bytes]):
    """trimesh's view of the files next to a mesh (OBJ .mtl, textures), read via the resolver."""

    def __init__(self, resolver: ResourceResolver, uri: str, base: Path | None) -> None:
        self._resolver = resolver
        self._directory = uri.rsplit("/", 1)[0] if "/" in uri else ""
        self._base = base

    def __getitem__(self, name: str) -> bytes:
        uri = f"{self._directory}/{name}" if self._directory else name
        try:
            return self._resolver.read(uri, self._base)
        except ConvertError as err:
            raise KeyError(name) from err

    def __iter__(self) -> Iterator[str]:
        return iter(())

    def __len__(self) -> int:
        return 0


def _mesh(
    mesh: yourdfpy.Mesh,
    color: npt.NDArray[np.uint8] | None,
    resolver: ResourceResolver,
    base: Path | None,
) -> rr.Mesh3D:
    import trimesh

    uri = mesh.filename
    if not isinstance(uri, str) or not uri:
        msg = "its <mesh> has no filename"
        raise ConvertError(msg)
    scale = _scale(mesh.scale)
    if not np.isfinite(scale).all():
        msg = f"{uri}: its scale {scale.tolist()} is not finite"
        raise ConvertError(msg)
    data = _read_mesh(uri, resolver, base)
    file_type = PurePosixPath(uri).suffix.lstrip(".").lower()
    try:
        loaded = trimesh.load(
            io.BytesIO(data),
            file_type=file_type,
            force="scene",
            resolver=_SiblingFiles(resolver, uri, base),
        )
    except Exception as err:
        # trimesh's loaders raise whatever their parser hits on a corrupt or unknown file; one
        # broken mesh must cost one visual, not the robot.
        kind = file_type or "a mesh"
        msg = f"{uri}: trimesh cannot load it as {kind} ({type(err).__name__}: {err})"
        raise ConvertError(msg) from err
    linear = file_type in _LINEAR_COLOUR_TYPES
    scene = loaded if isinstance(loaded, trimesh.Scene) else trimesh.Scene(loaded)
    parts = [
        part for part in scene.dump() if isinstance(part, trimesh.Trimesh) and len(part.faces) > 0
    ]
    if not parts:
        msg = f"{uri}: the file holds no triangles"
        raise ConvertError(msg)
    if len(parts) == 1:
        return _mesh3d(parts[0], scale, color, linear)
    merged = trimesh.util.concatenate(_uniform_visuals(parts, linear))
    assert isinstance(merged, trimesh.Trimesh)  # concatenating meshes gives a mesh
    return _mesh3d(merged, scale, color, linear)


def _scale(scale: float | npt.ArrayLike | None) -> npt.NDArray[np.float64]:
    return np.broadcast_to(np.asarray(1.0 if scale is None else scale, np.float64), (3,))


def _texture_image(material: Any) -> Any:
    return getattr(material, "image", None) or getattr(material, "baseColorTexture", None)


def _base_colour(material: Any, linear: bool) -> npt.NDArray[np.uint8]:
    """The material's colour in sRGB, the space of Rerun's colours."""
    rgba = np.asarray(material.main_color, np.uint8)
    if not linear:
        return rgba
    import trimesh

    srgb = trimesh.visual.color.linear_to_srgb(rgba[:3] / 255.0)
    return np.append(np.round(np.asarray(srgb) * 255.0), rgba[3]).astype(np.uint8)


def _image_of(part: trimesh.Trimesh) -> Any:
    visual: Any = part.visual
    return _texture_image(visual.material) if visual.kind == "texture" else None


def _uniform_visuals(parts: Sequence[trimesh.Trimesh], linear: bool) -> list[trimesh.Trimesh]:
    """``parts`` with visuals trimesh concatenates without changing a colour.

    Concatenating parts of several materials packs them into one texture, and trimesh bakes an
    untextured material's colour there as glTF's linear base colour (made sRGB): a Collada
    diffuse of 64/255 came out as 137/255. So an untextured material becomes vertex colours of
    its base colour or, when another part has a texture, a small image of it (trimesh misplaces
    the one-pixel ones it makes itself); a textured one keeps just its image, the one texture a
    Mesh3D has (trimesh's packing fails on a mix of material kinds)."""
    import PIL.Image
    import trimesh

    textured = any(_image_of(part) is not None for part in parts)
    for part in parts:
        visual: Any = part.visual
        if visual.kind != "texture":
            continue
        image, uv = _image_of(part), visual.uv
        if image is None:
            colour = _base_colour(visual.material, linear)
            if not textured:
                part.visual = trimesh.visual.ColorVisuals(
                    part, vertex_colors=np.tile(colour, (len(part.vertices), 1))
                )
                continue
            image = PIL.Image.new("RGBA", (4, 4), tuple(int(c) for c in colour))
            uv = np.full((len(part.vertices), 2), 0.5)
        material = trimesh.visual.material.SimpleMaterial(image=image)  # type: ignore[no-untyped-call]
        part.visual = trimesh.visual.TextureVisuals(uv=uv, material=material)  # type: ignore[no-untyped-call]
    return list(parts)


def _mesh3d(
    mesh: trimesh.Trimesh,
    scale: npt.NDArray[np.float64],
    color: npt.NDArray[np.uint8] | None,
    linear: bool,
) -> rr.Mesh3D:
    """Mesh3D of ``mesh`` scaled; the mesh's own colours win over the URDF material, as in RViz
    (Rerun multiplies the albedo factor into vertex colours and textures, so it is left out)."""
    positions = np.asarray(mesh.vertices, np.float64) * scale
    normals = np.asarray(mesh.vertex_normals, np.float64) / scale
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    triangles = np.asarray(mesh.faces, np.uint32)
    if np.prod(scale) < 0:
        # A mirroring scale turns the faces inside out; flip the winding back.
        triangles = triangles[:, ::-1]
    vertex_colors = None
    texcoords = None
    texture = None
    albedo = color
    visual: Any = mesh.visual
    if visual.kind in ("vertex", "face"):
        vertex_colors = np.asarray(visual.vertex_colors, np.uint8)
        albedo = None
    elif visual.kind == "texture":
        material = visual.material
        image = _texture_image(material)
        if image is not None and visual.uv is not None and len(visual.uv) == len(positions):
            # trimesh's uv origin is the bottom-left corner, Rerun's the top-left one.
            uv = np.asarray(visual.uv, np.float32)
            texcoords = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
            texture = np.asarray(image.convert("RGBA"))
            albedo = None
        elif getattr(material, "main_color", None) is not None:
            albedo = _base_colour(material, linear)
    return rr.Mesh3D(
        vertex_positions=positions.astype(np.float32),
        vertex_normals=normals.astype(np.float32),
        triangle_indices=triangles,
        vertex_colors=vertex_colors,
        vertex_texcoords=texcoords,
        albedo_texture=texture,
        albedo_factor=albedo,
    )
