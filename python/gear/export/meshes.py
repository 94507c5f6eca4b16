"""Visual meshes: a part's TSDF mesh cut down to a face budget, coloured by its Gaussians, with
vertex normals."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from gear.twin import VISIBLE_OPACITY

COLOR_NEIGHBOURS = 8  # Gaussians averaged per vertex (inverse-distance weights)
NO_GAUSSIANS_GREY = np.array([0.6, 0.6, 0.6])


def simplify(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """The mesh with at most `max_faces` faces (quadric edge collapse), cleaned of duplicate
    vertices and degenerate faces. Unchanged in shape when it already fits the budget."""
    import fast_simplification

    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)  # merge duplicate vertices
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) > max_faces:
        # The quadric decimation lands near, not exactly on, its target: aim slightly below.
        reduction = 1.0 - 0.98 * max_faces / len(mesh.faces)
        points, faces = fast_simplification.simplify(
            mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64), reduction)
        mesh = trimesh.Trimesh(points, faces, process=True)
        mesh.update_faces(mesh.nondegenerate_faces())
        mesh.remove_unreferenced_vertices()
        while len(mesh.faces) > max_faces:  # rare overshoot: drop the smallest faces
            mesh.update_faces(np.argsort(-mesh.area_faces)[:max_faces])
            mesh.remove_unreferenced_vertices()
    return mesh


def vertex_colors(vertices: np.ndarray, means: np.ndarray, rgb: np.ndarray,
                  opacity: np.ndarray) -> np.ndarray:
    """RGB [V,3] in [0,1] per vertex: the inverse-distance weighted mean colour of the nearest
    visible Gaussians of the same part (faint ones only when there are no visible ones)."""
    visible = opacity >= VISIBLE_OPACITY
    if visible.sum() >= 1:
        means, rgb = means[visible], rgb[visible]
    if len(means) == 0:
        return np.broadcast_to(NO_GAUSSIANS_GREY, (len(vertices), 3)).copy()
    k = min(COLOR_NEIGHBOURS, len(means))
    dist, idx = cKDTree(means).query(vertices, k=k)
    dist, idx = dist.reshape(len(vertices), k), idx.reshape(len(vertices), k)
    weights = 1.0 / np.maximum(dist, 1e-6)
    weights /= weights.sum(axis=1, keepdims=True)
    return np.clip(np.einsum("vk,vkc->vc", weights, rgb[idx]), 0.0, 1.0)


def visual_mesh(mesh: trimesh.Trimesh, max_faces: int, means: np.ndarray, rgb: np.ndarray,
                opacity: np.ndarray) -> trimesh.Trimesh:
    """The simplified mesh with RGBA vertex colours from the part's Gaussians and normals."""
    out = simplify(mesh, max_faces)
    colors = vertex_colors(out.vertices, means, rgb, opacity)
    rgba = np.concatenate([np.round(colors * 255), np.full((len(colors), 1), 255)], axis=1)
    out.visual = trimesh.visual.ColorVisuals(out, vertex_colors=rgba.astype(np.uint8))
    if out.is_watertight:  # only a closed mesh has an inside to point the normals away from
        out.fix_normals()
    _ = out.vertex_normals  # computed now so every writer exports the same normals
    return out
