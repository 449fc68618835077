"""A registration read back from its RESULT.json (``docs/formats.md``, "RESULT.json").

:meth:`Registration.to_dict` writes the file; this module is the other
direction, shared by :meth:`Registration.load` (scripts), the workspace
(which keeps each photo's last registration as a RESULT.json) and anything
else that needs the object back rather than the dict.
"""

from __future__ import annotations

import math
import os
from dataclasses import fields
from pathlib import Path
from typing import Sequence

from ..camera import Intrinsics, Pose
from ..errors import input_error
from ..io.records import Sigma
from ..prior import Prior, load_camera_and_pose
from .params import RegistrationParams
from .pipeline import Registration, Trial
from .uncertainty import Uncertainty

__all__ = ["load_registration", "registration_from_dict", "trial_from_dict"]

#: Trial fields converted from their stored form (the rest are taken as stored).
_TRIAL_CONVERTED = {"params", "q", "pose", "start_pose", "residual_flow_px", "seconds",
                    "correspondences", "uncertainty"}


def stored_number(value, default: float = math.nan) -> float:
    """A stored number; ``null`` (a non-finite number in strict JSON) is ``default``."""
    return default if value is None else float(value)


def pose_or_none(d) -> Pose | None:
    """A stored pose block, None for ``null``."""
    return None if d is None else Pose.from_dict(d)


def trial_from_dict(d: dict, source, start: Pose, correspondences=None) -> Trial:
    """A trial back from its dict (a trial of RESULT.json, or of a workspace's
    trials.json with its start pose; without one, ``start``).

    Parameters
    ----------
    d : dict
    source : path-like or None
        The file, for messages about its parameters.
    start : Pose
        The start pose when the dict has none.
    correspondences : Correspondences, optional
    """
    names = {f.name for f in fields(Trial)}
    kwargs = {k: v for k, v in d.items() if k in names and k not in _TRIAL_CONVERTED}
    kwargs.update(
        params=RegistrationParams.from_dict(d.get("params") or {}, source),
        q=stored_number(d.get("Q")), pose=pose_or_none(d.get("pose")),
        start_pose=pose_or_none(d.get("start_pose")) or start,
        residual_flow_px=stored_number(d.get("residual_flow_px"), math.inf),
        seconds=float(d.get("seconds") or 0.0), correspondences=correspondences)
    kwargs.setdefault("hints", [])
    kwargs["uncertainty"] = Uncertainty.from_dict(d.get("uncertainty"))
    return Trial(**kwargs)


def registration_from_dict(result: dict, prior: Prior, source=None,
                           trials: Sequence[Trial] | None = None,
                           assumptions: Sequence[str] = (),
                           timings_s: dict | None = None) -> Registration:
    """A :class:`Registration` from a RESULT.json's dict.

    Parameters
    ----------
    result : dict
        The RESULT.json object.
    prior : Prior
        The prior to complete from the result's ``prior`` block (its pose,
        sigma and assumptions; the camera is the result's).
    source : path-like, optional
        The file, for messages.
    trials : sequence of Trial, optional
        The trials as objects already held (a workspace's); default: read
        from the result.
    assumptions, timings_s
        What RESULT.json does not keep (a workspace's own record of them).
    """
    intrinsics = Intrinsics.from_dict(result["camera"])
    if trials is None:
        trials = [trial_from_dict(t, source, prior.pose) for t in result.get("trials") or []]
    prior_d = result.get("prior") or {}
    prior = Prior(intrinsics, pose_or_none(prior_d.get("pose")) or prior.pose,
                  sigma=Sigma(**{k: float(v) for k, v in (prior_d.get("sigma") or {}).items()}),
                  assumptions=[str(a) for a in prior_d.get("assumptions") or []],
                  sun=prior.sun, sun_source=prior.sun_source)
    quality = result.get("quality") or {}
    return Registration(
        status=str(result["status"]), photo=str(result.get("photo", "")),
        intrinsics=intrinsics, pose=Pose.from_dict(result["pose"]), prior=prior,
        metrics=dict(result.get("metrics") or {}), q=stored_number(quality.get("Q")),
        grade=str(quality.get("grade", "failed")), hints=list(quality.get("hints") or []),
        trials=list(trials), timings_s=dict(timings_s or result.get("timings_s") or {}),
        best_trial=result.get("best_trial"), assumptions=[str(a) for a in assumptions],
        uncertainty=Uncertainty.from_dict(result.get("uncertainty")))


def load_registration(path: str | os.PathLike) -> Registration:
    """Read a RESULT.json back into a :class:`Registration`.

    Raises
    ------
    InputError
        The file is missing, not JSON, not a RESULT.json (a sensor record has
        no solved pose), or a block of it is malformed.
    """
    path = Path(path)
    if not path.exists():
        raise input_error(path, "no such file")
    from ..io.records import read_json

    data = read_json(path)
    if not (isinstance(data, dict) and isinstance(data.get("pose"), dict)
            and "R" in data["pose"]):
        raise input_error(path, "not a RESULT.json (no solved 'pose.R'; a sensor record?)")
    intrinsics, pose, _, _ = load_camera_and_pose(path)  # validated camera and pose
    if data.get("status") not in ("registered", "failed"):
        raise input_error(path, f"field 'status' must be 'registered' or 'failed', got "
                          f"{data.get('status')!r}")
    try:
        return registration_from_dict(data, Prior(intrinsics, pose), source=path)
    except (KeyError, TypeError, ValueError) as exc:
        raise input_error(path, f"malformed result ({exc})") from None
