"""Which contact cushion Blender gets on a scene: the rule bench_sim and the accuracy study share.

Matched to our fabric's thickness (`blender.contact_settings(fabric, matched=True)`), both
simulators hold the cloth at the same distance from the collider, and Blender runs 1.3-2.2x
faster than with the study's 5 + 10 mm cushion (13.3 mm at rest). But matched, Blender's
default quality lets cloth through where it meets a collider fast (17-18 % of each falling sheet
through the sphere; 4.8 % of the walking denim t-shirt deeper than its thickness into the body:
`benchmarks/study_blender_contact.py`, `study_blender_reference.py`). So a scene gets the matched
cushion where Blender's quality 5 run keeps the cloth within the QA's deep-share bound with it,
else the study's, and says which.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the study's plan reads the rule's name without loading the simulator
    from datagen.study.run import Run
    from datagen.study.scenes import StudyScene

# The rule's name in a study part's signature: a part measured under another rule (every part
# before 2026-11-29 ran the study's cushion) is reported as measured with it.
CONTACT_RULE = "matched where Blender's quality 5 keeps the cloth out with it, else the study's"
STUDY_CUSHION_RULE = "the study's"  # what a signature without the key was measured with
TRIAL_QUALITY = 5  # Blender's default steps per frame: the quality the speed target names


@dataclass
class ContactChoice:
    matched: bool  # Blender runs the scene with the cushion matched to our thickness
    matched_deep_share: float  # the trial's largest share deeper than the fabric's thickness
    trial: Run  # Blender's TRIAL_QUALITY run with the matched cushion
    scene: StudyScene  # the scene the trial ran

    @property
    def name(self) -> str:
        return "matched" if self.matched else "study"

    def record(self) -> dict:
        """What a result keeps of the choice (a study part, a bench_sim row)."""
        return {"blender_contact": self.name,
                "blender_matched_deep_share": self.matched_deep_share}

    def run(self, scene: StudyScene, quality: int, **kwargs) -> Run:
        """Blender's run of `scene` at `quality` with the chosen cushion (the trial itself when
        it is that run)."""
        from datagen.study import blender as peer

        if self.matched and quality == TRIAL_QUALITY and scene is self.scene and not kwargs:
            return self.trial
        return peer.run_blender(scene, quality, matched_contact=self.matched, **kwargs)


def peer_deep_share(run: Run, scene: StudyScene) -> float:
    """The largest share of a Blender run's garment deeper in the collider than its thickness
    (metrics.scene_penetration, the QA's deep share), measured once per run and kept in its QA
    series, where the study's rows read ours."""
    from datagen.study.metrics import scene_penetration

    if "deep_share" not in run.qa:
        run.qa["deep_share"] = [scene_penetration(run.positions, scene)[1]]
    return run.qa["deep_share"][0]


def choose_contact(scene: StudyScene) -> ContactChoice:
    """Run Blender's trial on `scene` with the matched cushion and choose (see the module)."""
    from datagen.qa import DEEP_SHARE_MAX
    from datagen.study import blender as peer

    trial = peer.run_blender(scene, TRIAL_QUALITY, matched_contact=True)
    deep = peer_deep_share(trial, scene)
    return ContactChoice(deep <= DEEP_SHARE_MAX, deep, trial, scene)
