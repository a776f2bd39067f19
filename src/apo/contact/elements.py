"""Contact elements and states: the results of the search (paper 2.1).

A contact element pairs a feature of the grasped object G with one of the environment E
(vertex ``v``, edge ``e`` or face ``f``) with its contact point and the extreme rays of its
cone of separating normals; a contact state is the set of elements at one pose.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from apo.dof import ContactPoint
from apo.typing import FloatArray


class ContactKind(enum.StrEnum):
    """Kind of a contact element: grasped feature first, environment feature second.

    A ``str`` enum: ``ContactKind.VF == "VF"``, and it is written as ``"VF"`` in JSON.
    """

    VF = "VF"
    FV = "FV"
    EE = "EE"
    VE = "VE"
    EV = "EV"
    VV = "VV"


# A feature id: ("v" | "e" | "f", index into the Polyhedron's arrays).
Feature = tuple[str, int]

_set = object.__setattr__


@dataclass(frozen=True, init=False, slots=True)
class ContactElement(ContactPoint):
    """One contact element: a contact point with its normals and the features that make it.

    The one type of a contact element everywhere: the contact search returns it, the DOF
    analysis takes it (it is an :class:`apo.dof.ContactPoint`), and the task model stores it
    (``apo.task.Element`` is this class). Environment frame, metres.

    Attributes
    ----------
    kind : ContactKind
        Given as a :class:`ContactKind` or its string (``"VF"``).
    grasped : Feature
        Feature of the grasped object G, e.g. ``("v", 3)``.
    environment : Feature
        Feature of the environment object E.
    point : ndarray, shape (3,)
        Contact point in the environment frame.
    normals : ndarray, shape (M, 3)
        Extreme rays of the cone of separating normals (unit, from E towards G).

    Examples
    --------
    >>> import numpy as np
    >>> el = ContactElement("VF", ("v", 0), ("f", 2), np.zeros(3), np.array([[0.0, 0, 1]]))
    >>> el.kind is ContactKind.VF, el.key, el.singular
    (True, ('VF', ('v', 0), ('f', 2)), False)
    """

    kind: ContactKind
    grasped: Feature
    environment: Feature

    def __init__(
        self,
        kind: ContactKind | str,
        grasped: Feature,
        environment: Feature,
        point: FloatArray,
        normals: FloatArray,
    ) -> None:
        # The positional order (kind, grasped, environment, point, normals) predates the
        # ContactPoint base, whose fields come first in the dataclass. Slots, no __dict__:
        # a task of thousands of states places thousands of elements (the frozen dataclass
        # forbids setattr, so object's is called).
        _set(self, "kind", kind if type(kind) is ContactKind else ContactKind(kind))
        _set(self, "grasped", grasped)
        _set(self, "environment", environment)
        _set(self, "point", point)
        _set(self, "normals", normals)

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
        inclusion test compares these sets (docs/theory.md pitfalls).
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
