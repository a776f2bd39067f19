"""Robot motion from a task model: the skill program and the object's pose trajectory.

Planning only (no simulator here): :mod:`apo.motion.program` holds the types of the skill
program and its JSON form ``apo.motion/1`` (``docs/motion.md``), :mod:`apo.motion.planner`
the planner (:func:`plan`), :mod:`apo.motion.trajectory` the nominal pose trajectory.
"""

from apo.motion.planner import plan
from apo.motion.program import (
    END_CONDITIONS,
    SCHEMA,
    Alignment,
    Compliance,
    MotionSpace,
    PlanParameters,
    Primitive,
    PrimitiveKind,
    Profile,
    RotationType,
    Search,
    SkillProgram,
    StopCondition,
    Target,
    program_from_dict,
    program_to_dict,
)
from apo.motion.trajectory import Trajectory, trajectory

__all__ = [
    "END_CONDITIONS",
    "SCHEMA",
    "Alignment",
    "Compliance",
    "MotionSpace",
    "PlanParameters",
    "Primitive",
    "PrimitiveKind",
    "Profile",
    "RotationType",
    "Search",
    "SkillProgram",
    "StopCondition",
    "Target",
    "Trajectory",
    "plan",
    "program_from_dict",
    "program_to_dict",
    "trajectory",
]
