"""Contact elements and contact states between two posed polyhedra (paper 2.1, 4.3.1).

INTERFACE FIXED BY THE LEAD; the contact finding is being written.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


class ContactKind(enum.Enum):
    """Kind of a contact element: grasped feature first, environment feature second."""

    VF = "VF"
    FV = "FV"
    EE = "EE"
    VE = "VE"
    EV = "EV"
    VV = "VV"


# A feature id: ("v" | "e" | "f", index into the Polyhedron's arrays).
Feature = tuple[str, int]


@dataclass(frozen=True)
class ContactElement:
    """One contact element (environment frame, metres).

    Attributes
    ----------
    kind : ContactKind
    grasped : Feature
        Feature of the grasped object G, e.g. ``("v", 3)``.
    environment : Feature
        Feature of the environment object E.
    point : ndarray, shape (3,)
        Contact point in the environment frame.
    normals : ndarray, shape (M, 3)
        Extreme rays of the cone of separating normals (unit, from E towards G).
    """

    kind: ContactKind
    grasped: Feature
    environment: Feature
    point: FloatArray
    normals: FloatArray

    @property
    def singular(self) -> bool:
        """True if the element has more than one separating normal."""
        return int(self.normals.shape[0]) > 1

    @property
    def key(self) -> tuple[str, Feature, Feature]:
        """Hashable identity (kind and feature ids), stable across frames."""
        return (self.kind.value, self.grasped, self.environment)


@dataclass(frozen=True)
class ContactState:
    """The contact elements between G and E at one pose.

    Attributes
    ----------
    elements : tuple of ContactElement
        Sorted by ``key``.
    touching : frozenset of (Feature, Feature)
        Every (grasped feature, environment feature) pair within the threshold; Donald's
        inclusion test compares these sets (THEORY.md pitfalls).
    """

    elements: tuple[ContactElement, ...]
    touching: frozenset[tuple[Feature, Feature]]

    @property
    def singular(self) -> bool:
        """True if any element is singular."""
        return any(e.singular for e in self.elements)

    @property
    def key(self) -> frozenset[tuple[str, Feature, Feature]]:
        """Hashable identity of the state (the set of element keys)."""
        return frozenset(e.key for e in self.elements)
