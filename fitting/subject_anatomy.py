"""A subject folder's knee as the association model needs it (:class:`knee.models.fem.anatomy.KneeAnatomy`):
the CT bones and skin in the femur's anatomical frame (from the CT landmarks), cut to a band around the
knee (a denser skin coarsened to :data:`knee.models.fem.anatomy.SKIN_VERTICES_MOST` vertices), with the
collateral ligaments' insertions taken, in this order, from:

1. the CT attachment areas ``ct/areas/mcl_femur``, ``mcl_tibia``, ``lcl_femur``, ``lcl_tibia`` (centroids);
2. the prior (a fitted parameter set): its MCL link (the LCL is then placed where its length varies least
   along the prior's motion, :func:`knee.models.fem.scene.build_knee_model`);
3. estimates from the bones' shapes (:func:`knee.models.fem.anatomy.default_collaterals`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from knee.fitting.pipeline import anatomical_frames
from knee.fitting.subject import Subject
from knee.foundations.conventions import transform_points
from knee.foundations.errors import KneeInputError
from knee.models.fem.anatomy import (
    BAND_WIDTHS,
    KneeAnatomy,
    anatomy_in_femur_frame,
    clip_anatomy,
    clip_bones_to_skin,
    default_collaterals,
    working_skin,
)
from knee.models.mechanism.params import MechanismParams


def _ct_insertion(subject: Subject, ligament: str) -> np.ndarray | None:
    """(2, 3) femoral and tibial centroids of a ligament's CT attachment areas (CT frame), or None."""
    ends = []
    for bone in ("femur", "tibia"):
        try:
            ends.append(subject.area(f"{ligament}_{bone}", "ct").points.mean(axis=0))
        except KneeInputError as e:
            if "missing area" in str(e):
                return None
            raise
    return np.vstack(ends)


def subject_anatomy(subject: Subject, prior: MechanismParams | None = None, widths: float = BAND_WIDTHS) -> KneeAnatomy:
    """The subject's knee for the association model (see the module docstring); ``widths``: the band
    kept around the joint line, in femur widths. Raises :class:`KneeInputError` when the folder has no
    skin or the bones do not lie inside it."""
    if subject.skin is None:
        raise KneeInputError(f"subject {subject.root} has no ct/skin.stl: the association model needs the skin "
                             f"at the CT pose")
    frames = anatomical_frames(subject)
    Tf, Tt = frames["femur"], frames["tibia"]
    anatomy = anatomy_in_femur_frame(subject.ct["femur"], subject.ct["tibia"], subject.skin, Tf, Tt,
                                     mcl=_ct_insertion(subject, "mcl"), lcl=_ct_insertion(subject, "lcl"),
                                     name=subject.name)
    if anatomy.mcl is None and prior is not None:
        link = prior.link("mcl")
        anatomy = replace(anatomy, mcl=np.vstack([link.femur, transform_points(anatomy.tibia_pose, link.tibia[None])[0]]))
    anatomy = working_skin(clip_anatomy(clip_bones_to_skin(anatomy), widths))
    if anatomy.mcl is None or (anatomy.lcl is None and prior is None):
        mcl, lcl = default_collaterals(anatomy)
        anatomy = replace(anatomy, mcl=anatomy.mcl if anatomy.mcl is not None else mcl,
                          lcl=anatomy.lcl if anatomy.lcl is not None or prior is not None else lcl)
    try:
        anatomy.check()
    except KneeInputError as e:  # the model's check knows the surfaces, not the folder they came from
        raise KneeInputError(f"subject {subject.root}: {e}") from None
    return anatomy

