"""Recognition of a demonstration: poses -> contact states -> task model (paper section 4.3).

A package of the pipeline's stages, in the order they run (``docs/recognition.md``):

- :mod:`~apo.recognition.inputs`: checks of the pose sequence, the default threshold;
- :mod:`~apo.recognition.contacts`: the contact state observed at every frame;
- :mod:`~apo.recognition.distances`: feature distances of contact elements over frames;
- :mod:`~apo.recognition.costs`: the cost of every candidate state at every frame;
- :mod:`~apo.recognition.decoding`: Viterbi decoders (whole sequence, or fed block by block);
- :mod:`~apo.recognition.segmentation`: the two segmentation passes, block by block;
- :mod:`~apo.recognition.candidates`: one candidate analysed (corrected pose, closure, DOF);
- :mod:`~apo.recognition.bridges`: states between two that cannot follow each other;
- :mod:`~apo.recognition.analysis`: which candidates to analyse, direct-transition tests;
- :mod:`~apo.recognition.correction`: pose correction of frames under states (4.3.1);
- :mod:`~apo.recognition.build`: the task's states, transitions and rejected runs;
- :mod:`~apo.recognition.pipeline`: :func:`recognize` and :func:`recognize_frames`.

Everything is in metres, in the environment frame; poses ``X_EG`` are 4x4 matrices of the
grasped object G in the environment frame E.
"""

from apo.recognition.bridges import meet_elements
from apo.recognition.contacts import near_signatures
from apo.recognition.correction import CORRECTION_MAX_ITER, CORRECTION_TOL, correct_poses
from apo.recognition.decoding import viterbi, viterbi_uniform
from apo.recognition.distances import element_distances
from apo.recognition.inputs import (
    FAR_FACTOR,
    THRESHOLD_FRACTION,
    check_sequence,
    default_threshold,
)
from apo.recognition.pipeline import recognize, recognize_frames
from apo.recognition.types import CandidateState, Recognition, SegmentationCosts

__all__ = [
    "CORRECTION_MAX_ITER",
    "CORRECTION_TOL",
    "FAR_FACTOR",
    "THRESHOLD_FRACTION",
    "CandidateState",
    "Recognition",
    "SegmentationCosts",
    "check_sequence",
    "correct_poses",
    "default_threshold",
    "element_distances",
    "meet_elements",
    "near_signatures",
    "recognize",
    "recognize_frames",
    "viterbi",
    "viterbi_uniform",
]
