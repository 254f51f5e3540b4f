"""What a verification's costs decide: which hypothesis leads (the lowest mean cost over the
kept views, unless it is a flip the views do not agree on: :func:`lead_hypothesis`), and the
components' weights after it (:func:`reweight`). Pure functions on the costs."""

from __future__ import annotations

import numpy as np

from posefuse.estimator.core.geometry import rotation_angle

__all__ = ["lead_hypothesis", "reweight"]


def lead_hypothesis(
    per_view: np.ndarray,
    R_world_obj: np.ndarray,
    component: np.ndarray,
    variant: np.ndarray,
    component_weights: np.ndarray,
    *,
    flip_z: float | None,
    flip_min_views: int,
    flip_deg: float,
) -> int:
    """Which hypothesis leads: the lowest mean cost, unless it is a flip the views do not agree
    on.

    A flip is a hypothesis more than ``flip_deg`` from the favourite, the heaviest component as
    it is (the templates' evidence). On a photograph whose edges fit every hypothesis about as
    badly, half the views may prefer each of two poses, and the lowest mean cost is then a coin
    the views toss. So over ``flip_min_views`` views or more, a flip leads only where the per-view
    cost differences (favourite minus flip) have a mean of at least ``flip_z`` standard errors;
    otherwise the favourite leads. With fewer views the lowest mean cost leads (a second view
    plainly overturns a first view's flip), and so it does with ``flip_z`` None.

    Args:
        per_view: (H, V) costs; R_world_obj: (H, 3, 3) the hypotheses; component: (H,) index into
        the components; variant: (H,) 0 for a component as it is; component_weights: (C,).
    Returns:
        the index of the leading hypothesis.
    """
    cost = per_view.mean(axis=1)
    best = int(np.argmin(cost))
    V = per_view.shape[1]
    if flip_z is None or V < flip_min_views:
        return best
    favourite = np.flatnonzero(
        (component == int(np.argmax(component_weights))) & (np.asarray(variant) == 0)
    )
    if len(favourite) == 0:  # the heaviest component was not asked about
        return best
    fav = int(favourite[0])
    if fav == best:
        return best
    if rotation_angle(R_world_obj[fav].T @ R_world_obj[best]) <= np.deg2rad(flip_deg):
        return best
    gain = per_view[fav] - per_view[best]  # (V,) > 0 where the view prefers the flip
    standard_error = gain.std(ddof=1) / np.sqrt(V)
    return best if gain.mean() >= flip_z * standard_error else fav


def reweight(
    cost: np.ndarray,
    component: np.ndarray,
    component_weights: np.ndarray,
    n_views: int,
    temperature: float,
) -> np.ndarray:
    """(C,) the components' weights after a verification: each verified component by its best
    hypothesis' cost (``cost`` (H,), of ``component`` (H,)), ``exp(-V (cost - best) /
    temperature)``; the components not asked keep their weight as scaled by the worst verified
    cost (they cannot gain)."""
    comp_cost = np.full(len(component_weights), cost.max())
    np.minimum.at(comp_cost, component, cost)
    w = np.asarray(component_weights, float)
    scaled = w * np.exp(-n_views * (comp_cost - cost.min()) / temperature)
    return scaled / scaled.sum() if scaled.sum() > 0 else w
