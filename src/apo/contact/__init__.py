"""Contact elements and contact states between two posed polyhedra (paper 2.1, 4.3.1).

:func:`find_contacts` finds every contact element between the grasped object G and the
environment object E at a pose ``X_EG`` (pose of G in E's frame, metres): candidate points
are vertices of either object within a distance threshold of the other's surface and
crossings of non-parallel edges; each candidate is snapped to the lowest-dimensional feature
of each object within the threshold, the local solids there are split into convex pieces,
and every pair of pieces that touch gives one element whose separating normals are the
extreme rays of ``N = T_G* ∩ (-T_E*)`` (``docs/contacts.md``). :class:`ContactFinder`
caches per-model data for use over many frames and searches a whole sequence of poses at
once (:meth:`ContactFinder.find_batch`: every stage is a numpy pass over a block of frames
and over all candidate elements); :func:`find_contacts_naive` is the plain all-pairs
reference; :func:`element_residuals` gives the residuals ``f_i(X_EG)`` of the elements and
their Jacobians for pose correction (paper 4.3.1).

Everything is in the environment frame E, in metres; twists are ``[omega; v]`` applied on
the left (``docs/conventions.md``).

The package follows the steps of the search, one module each:

- :mod:`~apo.contact.elements`: the result types (contact kind, feature, element, state);
- :mod:`~apo.contact.thresholds`: default distance threshold and angular tolerance, pose checks;
- :mod:`~apo.contact.model_data`: per-model data, the local solid at each feature split into
  convex pieces with their tangent cones, and the k-d trees (computed once per model);
- :mod:`~apo.contact.distance_tests`: which features lie within the threshold of which
  vertices and edges (exact distances, pruned by bounding spheres or k-d trees);
- :mod:`~apo.contact.candidates`: candidate (G feature, E feature) pairs, each vertex
  snapped to its lowest-dimensional feature within the threshold, and crossing edges;
- :mod:`~apo.contact.separating_normals`: the extreme rays of ``T_G* ∩ (-T_E*)`` for each
  pair of convex pieces (vectorised common cases and the scalar reference);
- :mod:`~apo.contact.classification`: element kinds, grouping into elements, contact points;
- :mod:`~apo.contact.search`: :class:`ContactFinder` and the ``find_contacts*`` functions,
  the batched search over many poses;
- :mod:`~apo.contact.residuals`: residuals and Jacobians of elements for pose correction.
"""

from apo.contact.elements import ContactElement, ContactKind, ContactState, Feature
from apo.contact.residuals import element_residuals, residual_counts
from apo.contact.search import (
    ContactFinder,
    contact_points,
    find_contacts,
    find_contacts_batch,
    find_contacts_naive,
)
from apo.contact.thresholds import (
    DEFAULT_THRESHOLD_FRACTION,
    OBSERVED_THRESHOLD_FRACTION,
    default_angle_tolerance,
    default_threshold,
)

__all__ = [
    "DEFAULT_THRESHOLD_FRACTION",
    "OBSERVED_THRESHOLD_FRACTION",
    "ContactElement",
    "ContactFinder",
    "ContactKind",
    "ContactState",
    "Feature",
    "contact_points",
    "default_angle_tolerance",
    "default_threshold",
    "element_residuals",
    "find_contacts",
    "find_contacts_batch",
    "find_contacts_naive",
    "residual_counts",
]
