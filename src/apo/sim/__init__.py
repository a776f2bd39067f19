"""Execution of skill programs in MuJoCo (optional extra ``sim``): scene, hand, replay.

``docs/sim.md`` describes the scene (convex pieces, clearance, contact parameters), the
compliant hand, how each primitive is executed, and the verdict.
"""
