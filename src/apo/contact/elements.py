"""Contact elements and states: the results of the search (paper 2.1).

A contact element pairs a feature of the grasped object G with one of the environment E
(vertex ``v``, edge ``e`` or face ``f``) with its contact point and the extreme rays of its
cone of separating normals; a contact state is the set of elements at one pose.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from apo.typing import FloatArray


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


_CODE = {"v": 0, "e": 1, "f": 2}
_NAME = ("v", "e", "f")


_KIND_LIST = (
    ContactKind.VF,
    ContactKind.FV,
    ContactKind.EE,
    ContactKind.VE,
    ContactKind.EV,
    ContactKind.VV,
)
# Kind code of (G feature kind code, E feature kind code), -1 for no element.
_KIND_TABLE = np.full((3, 3), -1, dtype=np.int64)
for _code, _k in enumerate(_KIND_LIST):
    _KIND_TABLE[_CODE[_k.value[0].lower()], _CODE[_k.value[1].lower()]] = _code
# Sort ranks matching the tuple order of element keys (kind value, ("v" | "e" | "f", index)).
_KIND_RANK = np.argsort(np.argsort([k.value for k in _KIND_LIST]))
_FEATURE_RANK = np.argsort(np.argsort(_NAME))
