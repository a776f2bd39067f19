"""apo: Assembly Plan from Observation.

Watch a person assemble two rigid parts, recognise the demonstration as a task model
(contact states, DOF transitions, sub-skills, critical transitions) and generate the robot
motion that reproduces it. The method is Takamatsu et al., "Abstraction of Assembly Tasks to
Automatically Generate Robot Motion from Observation" (IPSJ Journal, 2005).

Heavy modules are imported lazily: ``import apo`` is cheap.
"""

from apo.errors import ApoError, GeometryError, InputFormatError, TrackingLostError

__all__ = ["ApoError", "GeometryError", "InputFormatError", "TrackingLostError", "__version__"]
__version__ = "0.1.0"
