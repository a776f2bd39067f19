"""Admissible-displacement cones and DOF indices of a contact state (paper section 2).

INTERFACE FIXED BY THE LEAD; the analysis is being written.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class ContactPoint:
    """One contact point with its separating normals (environment frame, metres).

    Attributes
    ----------
    point : ndarray, shape (3,)
        Contact point P_i.
    normals : ndarray, shape (M, 3)
        Unit separating normals F_i1..F_iM, pointing from the environment towards the
        grasped object. M > 1 makes the point singular.
    """

    point: FloatArray
    normals: FloatArray

    @property
    def singular(self) -> bool:
        """True if the point has more than one separating normal."""
        return int(self.normals.shape[0]) > 1


@dataclass(frozen=True)
class SpaceDof:
    """Maintaining / detaching / constraining DOF of one space (translation or all)."""

    maintaining: int
    detaching: int
    constraining: int


@dataclass(frozen=True)
class RotationDof(SpaceDof):
    """Rotation DOF; detaching split into type I (both ways) and type II (one way)."""

    detaching_type1: int = 0
    detaching_type2: int = 0


@dataclass(frozen=True)
class Restraining:
    """Restraining DOF r_t, r_r, r_a (paper section 3.5), over all elements and normals."""

    translation: int
    rotation: int
    all: int


@dataclass(frozen=True)
class DofGeometry:
    """Orthonormal bases (as rows) of the subspaces behind the numbers (environment frame).

    Attributes
    ----------
    translation_maintaining : ndarray, shape (m_t, 3)
        Translations that keep every contact (null space of R_t^T).
    translation_constraining : ndarray, shape (c_t, 3)
        Translation directions removed by the contacts (span of the lineality of cone(F)).
    translation_detaching : ndarray, shape (d_t, 3)
        Complement of the two above: translations that break some contact one way only.
    rotation_maintaining : ndarray, shape (m_r, 3)
        Rotation axes of maintaining twists (S0 parts of the maintaining twists).
    rotation_constraining : ndarray, shape (c_r, 3)
        Orthogonal complement of span(V_r).
    rotation_detaching : ndarray, shape (d_r, 3)
        The rest; ``rotation_detaching_type1`` (d_r1, 3) the two-way part.
    rotation_detaching_type1 : ndarray, shape (d_r1, 3)
    maintaining_twists : ndarray, shape (m_a, 6)
        Basis of maintaining twists ``[S0; S1]``.
    """

    translation_maintaining: FloatArray
    translation_detaching: FloatArray
    translation_constraining: FloatArray
    rotation_maintaining: FloatArray
    rotation_detaching: FloatArray
    rotation_detaching_type1: FloatArray
    rotation_constraining: FloatArray
    maintaining_twists: FloatArray


@dataclass(frozen=True)
class DofResult:
    """Every DOF index of a contact state (THEORY.md, paper sections 2.2 and 3.5).

    In a singular state the regular ``translation``/``rotation``/``all`` are all zero and the
    analysis of the non-singular elements is in ``singular_dof``; in a non-singular state
    ``singular_dof`` is all zero.
    """

    singular: bool
    translation: SpaceDof
    rotation: RotationDof
    all: SpaceDof
    singular_dof_translation: SpaceDof
    singular_dof_rotation: RotationDof
    singular_dof_all: SpaceDof
    restraining: Restraining
    geometry: DofGeometry = field(compare=False, repr=False)

    @property
    def fig25(self) -> tuple[int, int, int, int, int, int, int, int]:
        """The eight numbers as the paper's Fig. 25 prints them.

        Translation M, D, C, rotation M, D, C (singular variants in a singular state),
        translation restraining, rotation restraining.
        """
        t = self.singular_dof_translation if self.singular else self.translation
        r = self.singular_dof_rotation if self.singular else self.rotation
        return (
            t.maintaining, t.detaching, t.constraining,
            r.maintaining, r.detaching, r.constraining,
            self.restraining.translation, self.restraining.rotation,
        )  # fmt: skip

    def six(self, space: str) -> tuple[int, int, int, int, int, int]:
        """Return (M, D, C, SM, SD, SC) of ``space`` ('translation' or 'rotation'); sums to 3."""
        if space == "translation":
            a, b = self.translation, self.singular_dof_translation
        elif space == "rotation":
            a, b = self.rotation, self.singular_dof_rotation
        else:
            raise ValueError(f"space must be 'translation' or 'rotation', got {space!r}")
        return (
            a.maintaining, a.detaching, a.constraining,
            b.maintaining, b.detaching, b.constraining,
        )  # fmt: skip
