"""Convex pieces of a polyhedron for the simulator, and their shrinking by a clearance.

MuJoCo collides convex shapes only (a mesh geom is replaced by its convex hull), so each
model is cut into convex pieces first:

- *exact*: a piece that is not convex is cut along the plane of a face at one of its
  concave edges (``trimesh.intersections.slice_mesh_plane(cap=True)``), the plane that
  removes the most concave edges at once first, recursively, until every piece is convex.
  Every piece then lies exactly inside the model and the pieces tile its volume (the T-peg
  becomes two boxes, the U-slot three);
- *approximate*: when the exact cut does not finish within :data:`MAX_PIECES` pieces or a
  cut fails (curved or degenerate surfaces), the approximate convex decomposition of
  ``coacd`` (PyPI, optional) is used; its pieces may cross the surface by up to the
  ``tolerance`` reported in :class:`Decomposition`.

:func:`shrink_piece` offsets the faces of a piece that lie on the model's surface inwards by
a clearance (the half-spaces of the piece are moved and intersected again), so that the
simulated grasped object is smaller than its model by that gap on every side while the
cut faces inside the object stay where they are.

Lengths are metres, in the model's frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from apo.errors import GeometryError
from apo.geometry import Polyhedron
from apo.typing import FloatArray

__all__ = [
    "MAX_PIECES",
    "ConvexPiece",
    "Decomposition",
    "convex_pieces",
    "shrink_piece",
]

MAX_PIECES = 64
"""The exact cut gives up (and falls back to ``coacd``) beyond this many pieces."""

_REL_TOL = 1e-7
"""Relative (to the model's bounding diagonal) tolerance of the plane and volume tests."""


@dataclass(frozen=True)
class ConvexPiece:
    """One convex piece: its vertices and its bounding half-spaces ``normals @ x <= offsets``.

    Attributes
    ----------
    vertices : ndarray, shape (V, 3)
        Metres, model frame.
    normals : ndarray, shape (F, 3)
        Outward unit normals of the piece's facets.
    offsets : ndarray, shape (F,)
        Plane offsets, metres.
    surface : ndarray of bool, shape (F,)
        True where the facet lies on a face of the model (not a cut inside it).
    """

    vertices: FloatArray
    normals: FloatArray
    offsets: FloatArray
    surface: npt.NDArray[np.bool_]

    @property
    def volume(self) -> float:
        """Volume of the piece, cubic metres."""
        from scipy.spatial import ConvexHull

        return float(ConvexHull(self.vertices).volume)

    def contains(self, points: npt.ArrayLike, tol: float = 0.0) -> npt.NDArray[np.bool_]:
        """Return which points lie inside the piece (within ``tol`` metres)."""
        p = np.atleast_2d(np.asarray(points, dtype=np.float64))
        out: npt.NDArray[np.bool_] = np.all(p @ self.normals.T <= self.offsets + tol, axis=1)
        return out


@dataclass(frozen=True)
class Decomposition:
    """The convex pieces of a model.

    Attributes
    ----------
    pieces : tuple of ConvexPiece
    method : str
        ``"convex"`` (the model is convex), ``"exact"`` (plane cuts) or ``"coacd"``.
    tolerance : float
        Metres: how far a piece may reach outside the model (0 up to rounding for
        ``"convex"`` and ``"exact"``; the measured largest excursion for ``"coacd"``).
    """

    pieces: tuple[ConvexPiece, ...]
    method: str
    tolerance: float


def _trimesh(poly: Polyhedron) -> object:
    import trimesh

    tris = np.concatenate(poly.face_triangles)
    return trimesh.Trimesh(poly.vertices.copy(), tris, process=True)


def _is_convex(mesh: object, tol: float) -> bool:
    vol = float(mesh.volume)  # type: ignore[attr-defined]
    hull = float(mesh.convex_hull.volume)  # type: ignore[attr-defined]
    return hull - vol <= tol * max(hull, 1e-30)


def _piece_from_points(points: FloatArray, poly: Polyhedron, tol: float) -> ConvexPiece:
    """Convex piece spanned by ``points``; facets on a model face are marked ``surface``."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(points)
    eq = hull.equations  # rows (n, -d): n @ x - d <= 0 inside
    normals, offsets = eq[:, :3], -eq[:, 3]
    keep: list[int] = []
    for i in range(len(normals)):  # merge the coplanar facets of the hull
        if not any(
            normals[i] @ normals[j] > 1 - 1e-9 and abs(offsets[i] - offsets[j]) <= tol for j in keep
        ):
            keep.append(i)
    n, d = normals[keep], offsets[keep]
    surface = np.array(
        [
            bool(
                np.any(
                    (poly.face_normals @ n[i] > 1 - 1e-9)
                    & (np.abs(poly.face_offsets - d[i]) <= tol)
                )
            )
            for i in range(len(n))
        ]
    )
    return ConvexPiece(points[hull.vertices].copy(), n, d, surface)


def _cut_planes(poly: Polyhedron) -> list[tuple[FloatArray, float]]:
    """Planes of the faces at the model's concave edges, each once."""
    planes: list[tuple[FloatArray, float]] = []
    tol = _REL_TOL * poly.scale
    for e in np.flatnonzero(~poly.edge_convex):
        for f in poly.edge_faces[e]:
            n, d = poly.face_normals[f], float(poly.face_offsets[f])
            if not any(abs(abs(n @ m) - 1) < 1e-9 and abs(d - (n @ m) * c) <= tol
                       for m, c in planes):  # fmt: skip
                planes.append((n.copy(), d))
    return planes


def _best_plane(
    mesh: object, planes: list[tuple[FloatArray, float]], poly: Polyhedron, tol: float
) -> tuple[FloatArray, float] | None:
    """Return the plane through the most concave edges of ``mesh`` that cuts it in two."""
    V = np.asarray(mesh.vertices)  # type: ignore[attr-defined]
    concave = poly.edges[~poly.edge_convex]
    a, b = poly.vertices[concave[:, 0]], poly.vertices[concave[:, 1]]
    mid = 0.5 * (a + b)
    lo, hi = V.min(axis=0) - tol, V.max(axis=0) + tol
    inside = np.all((mid >= lo) & (mid <= hi), axis=1)
    best, best_count = None, 0
    for n, d in planes:
        s = V @ n - d
        if s.min() > -10 * tol or s.max() < 10 * tol:
            continue  # does not cut this piece
        on = inside & (np.abs(a @ n - d) <= tol) & (np.abs(b @ n - d) <= tol)
        count = int(on.sum())
        if count > best_count:
            best, best_count = (n, d), count
    return best


def _exact_pieces(poly: Polyhedron) -> list[object] | None:
    """Cut ``poly`` along concave-edge face planes until convex; None if that fails."""
    from trimesh.intersections import slice_mesh_plane

    tol = _REL_TOL * poly.scale
    planes = _cut_planes(poly)
    todo, done = [_trimesh(poly)], []
    while todo:
        mesh = todo.pop()
        if _is_convex(mesh, 1e-6):
            done.append(mesh)
            continue
        plane = _best_plane(mesh, planes, poly, tol)
        if plane is None or len(done) + len(todo) + 2 > MAX_PIECES:
            return None
        n, d = plane
        origin = n * d
        for side in (n, -n):
            try:
                part = slice_mesh_plane(  # type: ignore[no-untyped-call]
                    mesh, plane_normal=-side, plane_origin=origin, cap=True
                )
            except (ValueError, IndexError):
                return None
            if part is None or len(part.faces) < 4 or part.volume <= tol**2 * poly.scale:
                return None
            todo.append(part)
    return done


def _coacd_pieces(poly: Polyhedron, threshold: float) -> list[FloatArray]:
    try:
        import coacd
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise GeometryError(
            f"{poly.name}: the model is not a union of convex pieces cut along its face planes "
            "and the approximate decomposition needs coacd (pip install 'apo[sim]')"
        ) from exc
    tris = np.concatenate(poly.face_triangles)
    coacd.set_log_level("error")
    parts = coacd.run_coacd(coacd.Mesh(poly.vertices, tris), threshold=threshold)
    return [np.asarray(v, dtype=np.float64) for v, _ in parts]


def _excursion(pieces: list[ConvexPiece], poly: Polyhedron) -> float:
    """Largest distance (metres) of a piece vertex outside the model's surface."""
    import trimesh

    mesh = _trimesh(poly)
    V = np.concatenate([p.vertices for p in pieces])
    sd = trimesh.proximity.signed_distance(mesh, V)  # type: ignore[no-untyped-call]  # positive inside
    return float(max(0.0, -float(np.min(sd))))


def convex_pieces(
    poly: Polyhedron, *, method: str = "auto", coacd_threshold: float = 0.02
) -> Decomposition:
    """Cut a polyhedron into convex pieces (exactly where possible).

    Parameters
    ----------
    poly : Polyhedron
        The model (metres).
    method : {"auto", "exact", "coacd"}
        ``"auto"``: exact plane cuts, ``coacd`` if they fail; ``"exact"``: raise instead of
        falling back; ``"coacd"``: always the approximate decomposition.
    coacd_threshold : float
        ``coacd``'s concavity threshold (fraction of the model size).

    Returns
    -------
    Decomposition

    Raises
    ------
    GeometryError
        ``method="exact"`` and the model cannot be cut exactly, or a piece is degenerate.
    """
    tol = _REL_TOL * poly.scale
    if method not in ("auto", "exact", "coacd"):
        raise ValueError(f"method must be 'auto', 'exact' or 'coacd', got {method!r}")
    if method != "coacd":
        if not np.any(~poly.edge_convex):
            return Decomposition((_piece_from_points(poly.vertices, poly, tol),), "convex", 0.0)
        meshes = _exact_pieces(poly)
        if meshes is not None:
            pieces = tuple(
                _piece_from_points(np.asarray(m.vertices), poly, tol)  # type: ignore[attr-defined]
                for m in meshes
            )
            return Decomposition(pieces, "exact", 0.0)
        if method == "exact":
            raise GeometryError(f"{poly.name}: no exact decomposition along its face planes")
    pts = _coacd_pieces(poly, coacd_threshold)
    approx = [_piece_from_points(p, poly, tol) for p in pts if len(p) >= 4]
    return Decomposition(tuple(approx), "coacd", _excursion(approx, poly))


def shrink_piece(piece: ConvexPiece, clearance: float) -> ConvexPiece:
    """Move the surface facets of a piece inwards by ``clearance`` metres.

    The half-spaces of the facets on the model's surface are offset by ``clearance`` and
    intersected again with the cut facets (unchanged), so the piece loses a layer of
    that thickness wherever it is exposed.

    Raises
    ------
    GeometryError
        The piece is thinner than twice the clearance (nothing would be left).
    """
    from scipy.optimize import linprog
    from scipy.spatial import HalfspaceIntersection

    if clearance == 0:
        return piece
    d = piece.offsets - clearance * piece.surface
    # Chebyshev centre: an interior point as far as possible from every plane
    res = linprog(
        np.r_[np.zeros(3), -1.0],
        A_ub=np.c_[piece.normals, np.ones(len(d))],
        b_ub=d,
        bounds=[(None, None)] * 3 + [(0, None)],
        method="highs",
    )
    x = res.x
    if not res.success or x is None or x[3] <= 1e-9:
        raise GeometryError(
            f"a convex piece is thinner than twice the clearance ({clearance * 1e3:g} mm)"
        )
    hs = HalfspaceIntersection(np.c_[piece.normals, -d], x[:3])
    V = np.asarray(hs.intersections, dtype=np.float64)
    from scipy.spatial import ConvexHull

    hull = ConvexHull(V)
    return ConvexPiece(V[hull.vertices].copy(), piece.normals.copy(), d, piece.surface.copy())
