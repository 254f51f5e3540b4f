"""A picture of the verification step: a hypothesis the mixture led with, and the one the views
chose, drawn over two views of the track.

python -m posefuse.bench.verification_figure --dataset DIR [--scene N ...] --out FILE.png

The estimator runs over each scene with the oracle front end (as ``posefuse run-dataset``). The
figure shows the track whose verification overturned the mixture's lead by the largest angle
while the winner is right (ADD-sym < 0.1 d against the truth): red, the model's edges at the
mixture's lead; green, at the verified winner; in the first and the last view the track kept.
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np

from posefuse.estimator.verification.model_edges import pose_edges, project_edges


def _crop(image, uv_sets, margin=30):
    pts = np.concatenate([u for u in uv_sets if len(u)])
    x0, y0 = np.maximum(pts.min(axis=0).astype(int) - margin, 0)
    x1, y1 = pts.max(axis=0).astype(int) + margin
    return x0, y0, x1, y1


def _draw(image_bgr, uv, colour):
    for u, v in np.round(uv).astype(int):
        if 0 <= v < image_bgr.shape[0] and 0 <= u < image_bgr.shape[1]:
            cv2.circle(image_bgr, (u, v), 1, colour, -1, cv2.LINE_AA)


def main(argv=None) -> int:
    from posefuse.cli.run import ORACLE_CENTER_SIGMA
    from posefuse.estimator.core.geometry import rotation_angle
    from posefuse.estimator.tracker import Frame, MultiViewEstimator
    from posefuse.evaluation.dataset import load_dataset
    from posefuse.evaluation.oracle import OracleConfig, OracleFrontend
    from posefuse.evaluation.scores import pose_error

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("--scene", type=int, action="append", default=None)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    ds = load_dataset(args.dataset)
    front = OracleFrontend(
        ds, OracleConfig(center_sigma_px=ORACLE_CENTER_SIGMA, with_masks=True, seed=0)
    )
    best = None
    for sid in args.scene or ds.scene_ids:
        scene = ds.scene(sid)
        est = MultiViewEstimator(ds.catalog)
        views = {}
        for im in scene.im_ids:
            view = scene.view(im)
            image = scene.load_rgb(im)
            views[im] = (view, image)
            est.update(Frame(im, view.camera, view.T_world_cam, image), front.detect(view))
        last_view = views[scene.im_ids[-1]][0]
        for track in est.tracks.values():
            v = track.verdict
            if v is None or track.mixture is None or len(track.edge_views) < 2:
                continue
            lead = track.mixture.best()
            winner = v.R_world_obj[v.best]
            turned = float(rotation_angle(winner @ lead.R_world_obj.T))
            model = ds.catalog[track.obj_id]
            t = track.estimate.t_world_obj

            def T_cam_obj(R, view, t=t):
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = R, t
                return np.linalg.inv(view.T_world_cam) @ T

            # the winner must be right against some instance of the class in the last view
            errors = [
                pose_error(model, T_cam_obj(winner, last_view), g.T_cam_obj)
                for g in last_view.gts
                if g.obj_id == track.obj_id
            ]
            if not errors or min(errors) >= 0.1 * model.diameter:
                continue
            if best is None or turned > best[0]:
                best = (turned, sid, track, lead.R_world_obj, winner, views, model)
    if best is None:
        print("no track where verification overturned the mixture's lead")
        return 1
    turned, sid, track, R_lead, R_win, views, model = best
    est_edges = MultiViewEstimator(ds.catalog).poses.model_edges(track.obj_id)[0]
    tiles = []
    for ev in (track.edge_views[0], track.edge_views[-1]):
        view, image = views[ev.stamp_ns]
        bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        uvs = []
        for R, colour in ((R_lead, (40, 40, 230)), (R_win, (40, 200, 40))):
            T = np.linalg.inv(view.T_world_cam)
            R_cam = (T[:3, :3] @ R)[None]
            t_cam = (T[:3, :3] @ track.estimate.t_world_obj + T[:3, 3])[None]
            pts, dirs, active, _ = pose_edges(est_edges, R_cam, t_cam)
            uv, _, _ = project_edges(pts, dirs, R_cam, t_cam, view.camera.K)
            uvs.append(uv[0][active[0]])
            _draw(bgr, uvs[-1], colour)
        x0, y0, x1, y1 = _crop(bgr, uvs)
        tile = cv2.resize(bgr[y0:y1, x0:x1], None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
        cv2.putText(
            tile, f"view {view.im_id}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1
        )
        tiles.append(tile)
    h = max(t.shape[0] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, h - t.shape[0], 0, 4, cv2.BORDER_CONSTANT) for t in tiles]
    cv2.imwrite(args.out, np.hstack(tiles))
    print(
        f"scene {sid}, {track.object_id}: the mixture led with a rotation {np.rad2deg(turned):.0f} "
        f"degrees from the verified winner; wrote {args.out}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
