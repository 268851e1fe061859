"""Skill library, behaviour tree and skill decision engine (paper Sec. III-B, IV; Figs 3, 5, 7, 8).

Notation (symbols, shapes, units):
    M steps m = 0..M-1 of a segmentation; R routes (ordered step lists); d state dimension; B robots
    g_m       (d,)      attractor of step m (data units)
    A_m                 subtask space of step m: ``Segmentation.log_density`` / ``other_log_density``
    H2(x_r)   scalar    entropy threshold of step m's small-scale modulation (fit time)
    r_a       float     arrival radius: step m is complete when ||x - g_m|| < r_a (fraction of the data span)
    progress  (route, index): the robot's route and the position of its active step in it

Modules: :mod:`~lfd_torch.skills.library` (skills, learning, persistence), :mod:`~lfd_torch.skills.tree` (the
py_trees behaviour tree), :mod:`~lfd_torch.skills.engine` (decisions, batched ticks, rollouts),
:mod:`~lfd_torch.skills.arrival` (bounded arrival time: rate floor, speed cap), :mod:`~lfd_torch.skills.disturbances` (random pushes),
:mod:`~lfd_torch.skills.stability` (dV/dt < 0 on samples, every step and mode).
"""

from lfd_torch.skills.arrival import Arrival, rate_floor, speed_cap
from lfd_torch.skills.disturbances import PUSH_KINDS, PushPlan, random_pushes
from lfd_torch.skills.engine import Decision, EngineRollout, SkillEngine, TickResult
from lfd_torch.skills.library import LIBRARY_SCHEMA, Skill, SkillLibrary, default_fitter
from lfd_torch.skills.settings import SkillSettings
from lfd_torch.skills.stability import StabilityReport, check_stability, stability_samples
from lfd_torch.skills.tree import DecisionVisitor, SkillTree

__all__ = [
    "Arrival",
    "Decision",
    "DecisionVisitor",
    "EngineRollout",
    "LIBRARY_SCHEMA",
    "PUSH_KINDS",
    "PushPlan",
    "Skill",
    "SkillEngine",
    "SkillLibrary",
    "SkillSettings",
    "SkillTree",
    "StabilityReport",
    "TickResult",
    "check_stability",
    "default_fitter",
    "random_pushes",
    "rate_floor",
    "speed_cap",
    "stability_samples",
]
