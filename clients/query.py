"""Query the current poses of a running daemon: over HTTP or with a Zenoh get."""

from __future__ import annotations

import json
import urllib.request

import msgpack
import numpy as np
from scipy.spatial.transform import Rotation


def _get_json(url: str, timeout: float = 5.0):
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return json.loads(r.read())


def objects_http(base_url: str, timeout: float = 5.0) -> list[dict]:
    return _get_json(f"{base_url.rstrip('/')}/objects", timeout)


def objects_zenoh(session, cell: str = "posefuse", timeout: float = 5.0) -> list[dict]:
    from posefuse.service.keys import Keys

    key = Keys(cell).state
    for reply in session.get(key, timeout=timeout):
        if reply.ok is not None:
            msg = msgpack.unpackb(reply.ok.payload.to_bytes(), raw=False)
            return list(msg.get("objects", []))
    raise TimeoutError(f"no reply on {key}: is the daemon running?")


def table(objects: list[dict]) -> str:
    """A plain-text table of ObjectEstimate dicts, units in the headers, with a legend."""
    lines = [
        f"{'object_id':<18} {'status':<10} {'views':>5} {'conf':>5} {'verified':>8} {'ambig':>5}  "
        f"{'x (m)':>8} {'y (m)':>8} {'z (m)':>8}  {'roll (deg)':>10} {'pitch (deg)':>11} "
        f"{'yaw (deg)':>9}  {'sigma_t (mm)':>12}"
    ]
    for o in objects:
        rpy = Rotation.from_quat(o["q"]).as_euler("xyz", degrees=True)
        cov = np.array(o["cov"]).reshape(6, 6)
        sigma = np.sqrt(np.trace(cov[:3, :3])) * 1000
        t = o["t"]
        lines.append(
            f"{o['object_id']:<18} {o['status']:<10} {o['n_views']:>5} {o['confidence']:>5.2f} "
            f"{'yes' if o.get('verified') else 'no':>8} "
            f"{len(o.get('alternatives') or []) or '-':>5}  "
            f"{t[0]:>8.4f} {t[1]:>8.4f} {t[2]:>8.4f}  {rpy[0]:>10.1f} {rpy[1]:>11.1f} "
            f"{rpy[2]:>9.1f}  {sigma:>12.2f}"
        )
    lines += [
        "x, y, z: the object's origin in the world frame; roll, pitch, yaw: its rotation as",
        "extrinsic x-y-z Euler angles; conf: confidence in [0, 1]; sigma_t: square root of the",
        "trace of the translation covariance; verified: the pose is the one the object's views",
        "agree on (checked across them and refined), not only its rotation mixture's best;",
        "ambig: how many near-symmetric turns of the rotation the views cannot rule out (the",
        "alternatives of the ObjectEstimate, docs/protocol.md), '-' for none.",
    ]
    return "\n".join(lines)
