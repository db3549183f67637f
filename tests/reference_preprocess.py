"""The preprocessing estimators as they were before their speed-ups (commit cfd1140), kept verbatim where
they changed, as references for tests/estimators/test_preprocess_speed.py. Slow on purpose: never use them elsewhere."""

from __future__ import annotations

import numpy as np

from difareli.lighting import sh
from difareli.data.encodings import PART_INDEX
from difareli.estimators.bfm_fit import (FACEMESH_TO_IBUG68, JAW, BFMFit, BFMGeometry, _pose_step, _rodrigues,
                                         pose_from_rotation)
from difareli.estimators.geometry import NUM_VERTICES, orient_toward_viewer, tessellation_triangles
from difareli.estimators.light import SkinSHLight, light_direction
from difareli.estimators.loading import BadInput
from difareli.estimators.masks import _FACE_IDX, _FG_IDX, CHIN, FOREHEAD, FaceMeshSelfieMasks, face_part_polygons
from difareli.render.face_model import N_EXP, N_ID, PIVOT, FaceModel, FaceParams
from difareli.utils.imageops import LUMA
from difareli.render import OrthoCamera, Scene, render_gbuffer


def facemesh_to_68(landmarks: np.ndarray) -> np.ndarray:
    lm = np.asarray(landmarks, dtype=np.float64)
    return np.stack([lm[list(ids)].mean(0) for ids in FACEMESH_TO_IBUG68])


def fit_bfm(landmarks_xy, H, W, *, model=None, jaw_weight=0.25, sigma=0.01, iterations=8, polish=10) -> BFMFit:
    model = model or FaceModel.load()
    uv = np.asarray(landmarks_xy, dtype=np.float64)
    y = np.stack([2 * uv[:, 0] / W - 1, 1 - 2 * uv[:, 1] / H], axis=1)  # NDC
    mean = model.mean[model.landmarks].astype(np.float64)
    basis = np.c_[model.id_basis, model.exp_basis].astype(np.float64).reshape(-1, 3, N_ID + N_EXP)[model.landmarks]
    w = np.ones(68)
    w[JAW] = jaw_weight
    n_c = N_ID + N_EXP
    c = np.zeros(n_c)
    for _ in range(iterations):
        s, r, t = _pose_step(mean + basis @ c, y, w)
        a = np.einsum("ij,kjc->kic", r[:2], basis).reshape(-1, n_c)  # (136, 50)
        b = ((y - t) / s - mean @ r[:2].T).reshape(-1)
        sw = np.repeat(w, 2)
        c = np.linalg.solve(a.T @ (a * sw[:, None]) + sigma ** 2 * np.eye(n_c), a.T @ (sw * b))
    sqw, s0 = np.sqrt(np.repeat(w, 2)), s

    def residual(r_, s_, t_, c_):
        proj = s_ * (mean + basis @ c_) @ r_[:2].T + t_
        return np.r_[sqw * ((proj - y) / s0).reshape(-1), sigma * c_]

    lam = 1e-3
    cur = residual(r, s, t, c)
    for _ in range(polish):
        x_pts = mean + basis @ c  # (68, 3)
        xr = x_pts @ r.T  # rotated
        jac = np.zeros((136 + n_c, 6 + n_c))
        for k in range(3):  # d/dw_k of s (R_delta R x)_xy with R_delta = I + [w]x
            e = np.zeros(3)
            e[k] = 1.0
            jac[:136, k] = s * np.cross(e, xr)[:, :2].reshape(-1)
        jac[:136, 3] = (s * xr[:, :2]).reshape(-1)
        jac[:136, 4] = np.tile([1.0, 0.0], 68)
        jac[:136, 5] = np.tile([0.0, 1.0], 68)
        jac[:136, 6:] = s * np.einsum("ij,kjc->kic", r[:2], basis).reshape(-1, n_c)
        jac[:136] *= (sqw / s0)[:, None]
        jac[136:, 6:] = sigma * np.eye(n_c)
        g = jac.T @ cur
        h = jac.T @ jac
        step = np.linalg.solve(h + lam * np.diag(np.diag(h) + 1e-12), -g)
        r_new = _rodrigues(step[:3]) @ r
        s_new, t_new, c_new = s * np.exp(step[3]), t + step[4:6], c + step[6:]
        new = residual(r_new, s_new, t_new, c_new)
        if new @ new < cur @ cur:
            r, s, t, c, cur, lam = r_new, s_new, t_new, c_new, new, lam / 3
            if np.abs(step).max() < 1e-9:
                break
        else:
            lam *= 10
    params = FaceParams(c[:N_ID].copy(), c[N_ID:].copy(), pose_from_rotation(r))
    cam = OrthoCamera(s, *(t / s + (r @ PIVOT)[:2] - PIVOT[:2]))
    posed = model.build(params)[0][model.landmarks]
    proj = cam.project(posed, H, W)
    err = np.linalg.norm(proj - uv, axis=1)
    return BFMFit(params, cam, proj, float(np.sqrt((err ** 2).mean())), float(np.sqrt((err[17:] ** 2).mean())))


class ReferenceBFMGeometry(BFMGeometry):
    def __call__(self, ctx: dict, needed: set[str]) -> dict:
        image = ctx["image"]
        H, W = image.shape[:2]
        lm, notes = self.landmarks(ctx)
        fit = fit_bfm(facemesh_to_68(lm[:, :2]), H, W, **self.fit_options)
        if not fit.rmse_px <= self.max_rmse * max(H, W):
            raise BadInput(f"BFM fit failed: landmark RMSE {fit.rmse_px:.2f} px")
        model = FaceModel.load()
        verts = fit.cam.unproject(lm[:NUM_VERTICES, :2], 0.0, H, W)
        z = -lm[:NUM_VERTICES, 2] * 2.0 / (W * fit.cam.scale)
        bfm_z = model.build(fit.params)[0][model.landmarks].astype(np.float64)[17:, 2]
        mesh_z = facemesh_to_68(z[:, None])[17:, 0]
        verts[:, 2] = z + (bfm_z - mesh_z).mean()
        z_corr = float(np.corrcoef(bfm_z, mesh_z)[0, 1])
        info = {"rmse_px": round(fit.rmse_px, 3), "rmse_inner_px": round(fit.rmse_inner_px, 3),
                "pose_deg": np.round(fit.params.pose, 2).tolist(), "z_corr": round(z_corr, 3)}
        out = {"landmarks": lm, "shape": fit.params.shape_vector(), "cam": fit.cam.to_array(),
               "reprojection_px": fit.rmse_px, "bfm_fit": info, "notes": notes}
        if needed & {"scene", "gbuffer", "normal", "depth"}:
            scene = Scene.from_arrays(verts, orient_toward_viewer(verts, tessellation_triangles()))
            gb = render_gbuffer(scene, fit.cam, H, W)
            out.update(scene=scene, gbuffer=gb, normal=gb.normal.astype(np.float32),
                       depth=np.where(gb.hit, gb.depth, 0.0).astype(np.float32))
        return out


def is_grey(image, tolerance=4, share=0.01) -> bool:
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[-1] != 3:
        return False
    a = a.astype(np.int16)
    spread = a.max(-1) - a.min(-1)
    return bool(np.mean(spread > tolerance) <= share)


class ReferenceSkinSHLight(SkinSHLight):
    def skin_pixels(self, image, gbuffer, skin):
        import cv2

        r = max(1, int(round(self.erode * image.shape[0])))
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        m = cv2.erode(skin.astype(np.uint8), disk, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
        rgb = image.astype(np.float64) / 255.0
        return (m & gbuffer.hit & (gbuffer.normal[..., 2] > self.min_nz)
                & (rgb.max(-1) < self.saturated) & (rgb @ LUMA > self.dark))

    def fit(self, image, normal, mask, grey=None):
        grey = is_grey(image) if grey is None else bool(grey)
        y = image[mask].astype(np.float64) / 255.0
        n = normal[mask].astype(np.float64)
        albedo = self.albedo
        if grey:
            y = np.repeat((y @ LUMA)[:, None], 3, axis=1)
            albedo = np.full(3, float(self.albedo @ LUMA))
        if len(y) < self.min_pixels:
            raise BadInput(f"too few usable skin pixels for the light fit ({len(y)} < {self.min_pixels})")
        keep = np.ones(len(y), dtype=bool)
        for _ in range(2):
            light = sh.fit(y[keep], n[keep], albedo, ridge=self.ridge * keep.sum())
            if grey:
                light = np.repeat(light[:, :1], 3, axis=1)
            res = (y - albedo * sh.irradiance(light, n)) @ LUMA
            mad = 1.4826 * np.median(np.abs(res - np.median(res))) + 1e-6
            new = np.abs(res - np.median(res)) < self.clip_mads * mad
            if new.sum() < self.min_pixels or np.array_equal(new, keep):
                break
            keep = new
        pred = albedo * sh.irradiance(light, n[keep])
        obs = y[keep]
        lum_p, lum_o = pred @ LUMA, obs @ LUMA
        stats = {"pixels": int(keep.sum()), "rmse": float(np.sqrt(((pred - obs) ** 2).mean())),
                 "rel_rmse": float(np.sqrt(((lum_p - lum_o) ** 2).mean()) / max(lum_o.mean(), 1e-6)),
                 "corr": float(np.corrcoef(lum_p, lum_o)[0, 1]) if lum_o.std() > 0 else 0.0, "grey": grey}
        used = np.zeros(mask.size, dtype=bool)
        used[np.flatnonzero(mask)[keep]] = True
        return light.astype(np.float32), used.reshape(mask.shape), stats

    def __call__(self, ctx, needed):
        gb = ctx["gbuffer"]
        mask = self.skin_pixels(ctx["image"], gb, ctx["skin"])
        grey = is_grey(ctx["image"])
        light, used, stats = self.fit(ctx["image"], gb.normal, mask, grey=grey)
        stats["direction"] = light_direction(light)
        shading = np.asarray(sh.shading_reference(light, gb.normal, mask=gb.hit), dtype=np.float32)
        notes = ["grey photo: light fitted on the luminance, equal in R, G and B"] if grey else []
        return {"light": light, "shading": shading, "fit_pixels": used, "light_fit": stats, "notes": notes,
                "albedo_prior": np.full(3, float(self.albedo @ LUMA)) if grey else self.albedo}


def fill(poly_xy, shape):
    from skimage.draw import polygon

    m = np.zeros(shape, dtype=bool)
    rr, cc = polygon(poly_xy[:, 1] - 0.5, poly_xy[:, 0] - 0.5, shape)
    m[rr, cc] = True
    return m


class ReferenceMasks(FaceMeshSelfieMasks):
    def face_labels(self, lm_xy, shape):
        labels = np.zeros(shape, dtype=np.uint8)
        for name, poly in face_part_polygons(lm_xy).items():
            labels[fill(poly, shape)] = PART_INDEX[name]
        return labels

    def __call__(self, ctx, needed):
        image = ctx["image"]
        H, W = image.shape[:2]
        lm = np.asarray(ctx["landmarks"])[:, :2]
        labels = self.face_labels(lm, (H, W))
        face = labels > 0
        out = {"skin": labels == PART_INDEX["skin"], "face_mask": np.isin(labels, _FACE_IDX)}
        if needed & {"masks", "background", "person"}:
            person = self.person(image) > self.person_threshold
            rows, cols = np.mgrid[0:H, 0:W] + 0.5
            chin = lm[CHIN]
            h = max(chin[1] - lm[FOREHEAD, 1], 1.0)
            w = max(np.ptp(lm[:, 0]), 1.0)
            jaw = 0.5 * (chin[1] + 0.5 * (lm[61, 1] + lm[291, 1]))
            rest = person & ~face
            above = rows < jaw
            neck = (rest & ~above & (rows < chin[1] + self.neck_depth * h)
                    & (np.abs(cols - chin[0]) < self.neck_halfwidth * w))
            labels[rest & above] = PART_INDEX["hair"]
            labels[neck] = PART_INDEX["neck"]
            labels[rest & ~above & ~neck] = PART_INDEX["clothes"]
            if self.colour:
                self.refine(image, labels, lm, rows, cols, h, w, jaw)
            out.update(masks=labels, person=person,
                       background=np.where(np.isin(labels, _FG_IDX)[..., None], 0, image).astype(np.uint8))
        return out

    def refine(self, image, labels, lm, rows, cols, h, w, jaw):
        from scipy import ndimage
        from skimage.color import rgb2lab

        lab = rgb2lab(image)
        skin = labels == PART_INDEX["skin"]
        if skin.sum() < 50:
            return
        ref = np.median(lab[skin], axis=0)
        chroma = np.hypot(lab[..., 1] - ref[1], lab[..., 2] - ref[2])
        chin = lm[CHIN]
        below = np.isin(labels, [PART_INDEX["neck"], PART_INDEX["clothes"]])
        zone = (below & (rows < chin[1] + self.neck_max_depth * h)
                & (np.abs(cols - chin[0]) < self.neck_max_halfwidth * w))
        skinlike = zone & (chroma < self.skin_chroma) & (lab[..., 0] > ref[0] - self.skin_dark)
        skinlike = ndimage.binary_opening(skinlike, iterations=1)
        comp, n = ndimage.label(skinlike)
        seed = skinlike & (rows < chin[1] + 0.15 * h) & (np.abs(cols - chin[0]) < 0.25 * w)
        keep = np.unique(comp[seed])
        neck = np.isin(comp, keep[keep > 0])
        if neck.sum() > 0.02 * h * w:
            neck = ndimage.binary_closing(neck, iterations=2) & below
            labels[below] = PART_INDEX["clothes"]
            labels[neck] = PART_INDEX["neck"]
        hair = labels == PART_INDEX["hair"]
        eyes_y = 0.5 * (lm[33, 1] + lm[263, 1])
        xs = lm[:, 0]
        beside = hair & (rows > eyes_y) & (rows < jaw) & (((cols < xs.min()) & (cols > xs.min() - 0.35 * w))
                                                         | ((cols > xs.max()) & (cols < xs.max() + 0.35 * w)))
        top = hair & (rows < lm[FOREHEAD, 1])
        if beside.sum() < 30 or top.sum() < 30:
            return
        hair_ref = np.median(lab[beside], axis=0)
        unlike = top & ((np.hypot(lab[..., 1] - hair_ref[1], lab[..., 2] - hair_ref[2]) > self.hat_chroma)
                        | (np.abs(lab[..., 0] - hair_ref[0]) > self.hat_lightness))
        unlike = ndimage.binary_opening(unlike, iterations=2)
        if unlike.sum() >= self.hat_min_share * top.sum():
            comp, n = ndimage.label(unlike)
            keep = []
            for i, sl in enumerate(ndimage.find_objects(comp), start=1):
                area = (comp[sl] == i).sum()
                bw, bh = sl[1].stop - sl[1].start, sl[0].stop - sl[0].start
                if area >= 0.05 * top.sum() and bw >= self.hat_min_width * w and area >= 0.5 * bw * bh:
                    keep.append(i)
            if keep:
                labels[ndimage.binary_closing(np.isin(comp, keep), iterations=2) & hair] = PART_INDEX["hat"]
