"""Part masks over ``MASK_PARTS`` from FaceMesh outlines plus mediapipe selfie segmentation.

No face parser with shipped weights exists offline (OFFLINE.md), so:

- face parts are polygons of FaceMesh landmark sets (``face_mesh_connections``): the face oval is ``skin``,
  painted over in this order by ``nose`` (convex hull of FACEMESH_NOSE), brows, eyes, ``u_lip``/``l_lip`` (between the
  outer and inner lip contours) and ``mouth`` (inside the inner contour). Left/right are the subject's, as in mediapipe
  and SynthFaces (``l_eye`` is on the image right).
- non-facial parts come from the selfie-segmentation person mask (``person``, probability > 0.5) outside
  the face oval, by fixed rules in units of the face height ``h`` (forehead top to chin) and width ``w``:
  ``hair`` = person pixels above the jaw line (midway between mouth corners and chin); ``neck`` = person
  pixels below it, less than ``neck_depth * h`` under the chin and within ``neck_halfwidth * w`` of the
  chin horizontally; ``clothes`` = the remaining person pixels below the jaw line. ``hat`` is never
  produced (nothing tells a hat from hair), ears count as hair or skin depending on where they fall.
"""

from __future__ import annotations

import functools

import numpy as np

from difareli.data.encodings import FACE_PARTS, FOREGROUND_PARTS, PART_INDEX
from difareli.errors import UserError
from difareli.utils.imageops import rgb2lab_u8 as rgb2lab

# Lip contours (FACEMESH_LIPS is four chains; tests check these against it), corners first and last.
LIPS_OUTER_UPPER = (61, 185, 40, 39, 37, 0, 267, 269, 270, 409, 291)
LIPS_OUTER_LOWER = (61, 146, 91, 181, 84, 17, 314, 405, 321, 375, 291)
LIPS_INNER_UPPER = (78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308)
LIPS_INNER_LOWER = (78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308)
CHIN, FOREHEAD = 152, 10
_FACE_IDX = np.array([PART_INDEX[p] for p in FACE_PARTS])
_FG_IDX = np.array([PART_INDEX[p] for p in FOREGROUND_PARTS])
# Label -> bool lookups: ``lut[labels]`` is np.isin(labels, idx) at a fraction of the cost.
_FACE_LUT = np.isin(np.arange(256), _FACE_IDX)
_FG_LUT = np.isin(np.arange(256), _FG_IDX)
_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=np.uint8)  # scipy.ndimage's default structure


def erode(mask: np.ndarray, iterations: int = 1) -> np.ndarray:
    """``ndimage.binary_erosion(mask, iterations=...)`` (cross element, outside the image counts as False)
    through OpenCV, ~10x faster."""
    import cv2

    m = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
    return cv2.erode(m, _CROSS, iterations=iterations, borderType=cv2.BORDER_CONSTANT, borderValue=0).view(bool)


def dilate(mask: np.ndarray, iterations: int = 1) -> np.ndarray:
    """``ndimage.binary_dilation(mask, iterations=...)`` (cross element) through OpenCV."""
    import cv2

    m = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
    return cv2.dilate(m, _CROSS, iterations=iterations, borderType=cv2.BORDER_CONSTANT, borderValue=0).view(bool)


def opening(mask: np.ndarray, iterations: int = 1) -> np.ndarray:
    """``ndimage.binary_opening``: erosion, then dilation."""
    return dilate(erode(mask, iterations), iterations)


def closing(mask: np.ndarray, iterations: int = 1) -> np.ndarray:
    """``ndimage.binary_closing``: dilation, then erosion (which, as scipy's, erodes from the image border)."""
    return erode(dilate(mask, iterations), iterations)


def chains(edges) -> list[list[int]]:
    """Split an undirected edge set into its cycles and simple paths (vertex lists; a cycle is not closed)."""
    adj: dict[int, list[int]] = {}
    for a, b in edges:
        adj.setdefault(a, []).append(b)
        adj.setdefault(b, []).append(a)
    seen: set[int] = set()
    out = []
    # Paths first, from their endpoints (degree 1); whatever is left consists of cycles.
    starts = [v for v in sorted(adj) if len(adj[v]) == 1] + sorted(adj)
    for s in starts:
        if s in seen:
            continue
        path, prev, cur = [s], None, s
        seen.add(s)
        while True:
            nxt = [v for v in adj[cur] if v != prev and v not in seen]
            if not nxt:
                break
            prev, cur = cur, nxt[0]
            seen.add(cur)
            path.append(cur)
        out.append(path)
    return out


@functools.lru_cache(maxsize=32)
def _chains(edges: frozenset) -> tuple[tuple[int, ...], ...]:
    return tuple(map(tuple, chains(edges)))  # topology only: the same for every image


def outline(edges, points_xy: np.ndarray) -> list[int]:
    """One closed outline from a connection set: its cycle, or two paths joined end to end."""
    parts = [list(p) for p in _chains(frozenset(edges))]
    if len(parts) == 1:
        return parts[0]
    if len(parts) != 2:
        raise UserError(f"expected one cycle or two paths, got {len(parts)} chains")
    a, b = parts
    # Join so that the closing gaps are short: a's end meets b's start.
    if np.linalg.norm(points_xy[a[-1]] - points_xy[b[0]]) > np.linalg.norm(points_xy[a[-1]] - points_xy[b[-1]]):
        b = b[::-1]
    return a + b


def hull(edges, points_xy: np.ndarray) -> list[int]:
    """Vertices of a connection set's 2-D convex hull, in order (FACEMESH_NOSE is a bridge plus two
    partial sides, not an outline)."""
    from scipy.spatial import ConvexHull

    idx = np.array(sorted({i for e in edges for i in e}))
    return idx[ConvexHull(points_xy[idx]).vertices].tolist()


def fill(poly_xy: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Bool mask of pixels whose centres lie inside the polygon or on its boundary (continuous pixel
    coordinates): the rule of ``skimage.draw.polygon`` (O'Rourke's crossing test), one scanline per row instead
    of one test per pixel (~4x faster; equal to skimage on the tests' photos and on integer polygons, where
    every centre is a vertex, on an edge, or off it by far more than rounding)."""
    m = np.zeros(shape, dtype=bool)
    r0, c0, box = fill_box(poly_xy, shape)
    m[r0:r0 + box.shape[0], c0:c0 + box.shape[1]] = box
    return m


def fill_box(poly_xy: np.ndarray, shape: tuple[int, int]) -> tuple[int, int, np.ndarray]:
    """:func:`fill` within the polygon's bounding box: (first row, first column, bool box mask)."""
    H, W = shape
    r, c = poly_xy[:, 1] - 0.5, poly_xy[:, 0] - 0.5  # vertices in pixel-index units
    r0, r1 = int(max(0, r.min())), min(H - 1, int(np.ceil(r.max())))  # skimage's box
    c0, c1 = int(max(0, c.min())), min(W - 1, int(np.ceil(c.max())))
    if r1 < r0 or c1 < c0:
        return 0, 0, np.zeros((0, 0), dtype=bool)
    rows = np.arange(r0, r1 + 1, dtype=np.float64)[:, None]
    prev = np.arange(-1, len(r) - 1)  # edge (i - 1, i), as skimage walks them
    y0, y1 = r - rows, r[prev] - rows  # relative to each row: (R, E)
    xa, xb = c, c[prev]
    right, left = (y0 > 0) != (y1 > 0), (y0 < 0) != (y1 < 0)  # straddles the row (the two senses of skimage)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = (xa * y1 - xb * y0) / (y1 - y0)  # column of the crossing
    n = c1 - c0 + 2
    ri, ei = np.nonzero(right)
    # Right crossings (xi > column) counted at the first column they do not reach; left ones (xi < column) at
    # the first column past them; cumulative sums then give both counts at every column.
    k = np.clip(np.ceil(xi[ri, ei]) - c0, 0, n - 1).astype(np.intp)
    r_cross = np.bincount(ri * n + k, minlength=len(rows) * n).reshape(-1, n)[:, ::-1].cumsum(1)[:, ::-1][:, 1:]
    li, ej = np.nonzero(left)
    k = np.clip(np.floor(xi[li, ej]) + 1 - c0, 0, n - 1).astype(np.intp)
    l_cross = np.bincount(li * n + k, minlength=len(rows) * n).reshape(-1, n).cumsum(1)[:, :-1]
    # Inside: an odd count of right crossings; on an edge: the two counts' parities differ. Both are drawn.
    box = ((r_cross | l_cross) & 1).astype(bool)
    on_vertex = (np.abs(r - np.round(r)) < 1e-12) & (np.abs(c - np.round(c)) < 1e-12)  # also drawn
    vr, vc = np.round(r[on_vertex]).astype(int) - r0, np.round(c[on_vertex]).astype(int) - c0
    inside = (vr >= 0) & (vr < box.shape[0]) & (vc >= 0) & (vc < box.shape[1])
    box[vr[inside], vc[inside]] = True
    return r0, c0, box


def face_part_polygons(lm_xy: np.ndarray) -> dict[str, np.ndarray]:
    """Polygons (K, 2) in pixel coordinates of the face parts, in painting order."""
    from mediapipe.python.solutions import face_mesh_connections as fmc

    def poly(idx):
        return lm_xy[list(idx)]

    return {
        "skin": poly(outline(fmc.FACEMESH_FACE_OVAL, lm_xy)),
        "nose": poly(hull(fmc.FACEMESH_NOSE, lm_xy)),
        "l_brow": poly(outline(fmc.FACEMESH_LEFT_EYEBROW, lm_xy)),
        "r_brow": poly(outline(fmc.FACEMESH_RIGHT_EYEBROW, lm_xy)),
        "l_eye": poly(outline(fmc.FACEMESH_LEFT_EYE, lm_xy)),
        "r_eye": poly(outline(fmc.FACEMESH_RIGHT_EYE, lm_xy)),
        "u_lip": poly(LIPS_OUTER_UPPER + LIPS_INNER_UPPER[::-1]),
        "l_lip": poly(LIPS_OUTER_LOWER + LIPS_INNER_LOWER[::-1]),
        "mouth": poly(LIPS_INNER_UPPER + LIPS_INNER_LOWER[::-1]),
    }


class FaceMeshSelfieMasks:
    """Estimator: part label map ``masks``, ``face_mask``, ``background`` and the ``skin`` pixels."""

    provides = ("masks", "face_mask", "background", "skin", "person")
    requires = ("image", "landmarks")

    def __init__(self, person_threshold: float = 0.5, neck_depth: float = 0.45, neck_halfwidth: float = 0.4,
                 model_selection: int = 0, colour: bool = True, skin_chroma: float = 14.0, skin_dark: float = 45.0,
                 neck_max_depth: float = 0.9, neck_max_halfwidth: float = 0.6, hat_chroma: float = 20.0,
                 hat_lightness: float = 40.0, hat_min_share: float = 0.15, hat_min_width: float = 0.6,
                 forehead_height: float = 0.35):
        self.person_threshold = person_threshold
        self.neck_depth = neck_depth
        self.neck_halfwidth = neck_halfwidth
        self.model_selection = model_selection
        self.colour, self.skin_chroma, self.skin_dark = colour, skin_chroma, skin_dark
        self.neck_max_depth, self.neck_max_halfwidth = neck_max_depth, neck_max_halfwidth
        self.hat_chroma, self.hat_lightness, self.hat_min_share = hat_chroma, hat_lightness, hat_min_share
        self.hat_min_width = hat_min_width
        self.forehead_height = forehead_height
        self._seg = None

    def person(self, image: np.ndarray) -> np.ndarray:
        """Selfie-segmentation person probability (H, W) in [0, 1]."""
        if self._seg is None:
            import mediapipe as mp

            self._seg = mp.solutions.selfie_segmentation.SelfieSegmentation(model_selection=self.model_selection)
        return np.asarray(self._seg.process(np.ascontiguousarray(image)).segmentation_mask, dtype=np.float32)

    def face_labels(self, lm_xy: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """uint8 label map with the face parts painted, background elsewhere."""
        labels = np.zeros(shape, dtype=np.uint8)
        for name, poly in face_part_polygons(lm_xy).items():
            r0, c0, box = fill_box(poly, shape)
            labels[r0:r0 + box.shape[0], c0:c0 + box.shape[1]][box] = PART_INDEX[name]
        return labels

    def __call__(self, ctx: dict, needed: set[str]) -> dict:
        image = ctx["image"]
        H, W = image.shape[:2]
        lm = np.asarray(ctx["landmarks"])[:, :2]
        labels = self.face_labels(lm, (H, W))
        face = labels > 0
        out = {"skin": labels == PART_INDEX["skin"], "face_mask": _FACE_LUT[labels]}
        if needed & {"masks", "background", "person"}:
            person = self.person(image) > self.person_threshold
            # Pixel-centre rows (H, 1) and columns (1, W): every use broadcasts them.
            rows, cols = np.arange(H)[:, None] + 0.5, np.arange(W)[None, :] + 0.5
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
                # Crop pixels past the photo's edge are a reflection of it (``align.warp_quad``): the colour
                # rules read only the real ones (the pipeline's ``inside``; all pixels where there is none).
                self.refine(image, labels, lm, rows, cols, h, w, jaw, real=ctx.get("inside"))
            out.update(masks=labels, person=person,
                       background=np.where(_FG_LUT[labels][..., None], 0, image).astype(np.uint8))
        return out

    def forehead(self, image, labels, lm, rows, cols, h, w, ref, rgb2lab, real=None) -> None:
        """Forehead skin above FaceMesh's oval (the oval stops below the hairline) is ``skin``, not ``hair``:
        skin-coloured person pixels (the neck rule's colour test) above the oval, within ``forehead_height * h``
        of its top and the face's width, connected to the oval's top edge. Labelled ``hair`` (and, unlike the hair
        beside the face, ``hat``) it was a grey band or a bright block across the forehead of the relight.
        ``real``: bool mask of the crop pixels inside the photo (None: all), the only ones the hair is sampled from."""
        from scipy import ndimage

        if self.forehead_height <= 0:  # the rule off (the masks before it)
            return
        oval = _FACE_LUT[labels]
        top = lm[FOREHEAD, 1]
        xs = lm[:, 0]
        zone = ((labels == PART_INDEX["hair"]) & (rows < top + 0.1 * h) & (rows > top - self.forehead_height * h)
                & (cols > xs.min()) & (cols < xs.max()))
        if not zone.any():
            return
        lab = rgb2lab(image[zone])
        skinlike = np.zeros_like(zone)
        near = ((np.hypot(lab[:, 1] - ref[1], lab[:, 2] - ref[2]) < self.skin_chroma)
                & (np.abs(lab[:, 0] - ref[0]) < self.skin_dark))
        # Light hair can pass the skin colour test (the astronaut's blonde hair did): a pixel is forehead skin only
        # if it is also closer in colour to the skin than to the hair beside the face.
        # Only hair in the photo counts: on a tight crop the "hair" above the zone is the padding, a reflection of
        # the forehead itself, and comparing with it refused the forehead (a hat block came back). Where the
        # photo shows nothing above the zone there is nothing to compare with, not even the hair beside the face
        # (as light as the astronaut's forehead, it refused it all): the guard stands down.
        hairy = labels == PART_INDEX["hair"]
        if real is not None:
            hairy = hairy & real
        band = (rows <= top - self.forehead_height * h) & (cols > xs.min()) & (cols < xs.max())
        blind = real is not None and band.any() and not (band & real).any()  # all padding above the zone
        above = hairy & band
        side = hairy & (rows > top) & (rows < top + 0.5 * h) & ((cols < xs.min()) | (cols > xs.max()))
        for other in () if blind else (above, side):  # the hair above the zone, else beside the face
            if other.sum() >= 30:
                hair = np.median(rgb2lab(image[other]), axis=0)
                near &= np.linalg.norm(lab - ref, axis=1) < np.linalg.norm(lab - hair, axis=1)
                break
        skinlike[zone] = near
        skinlike = opening(skinlike, 1)
        comp, n = ndimage.label(skinlike)
        seed = skinlike & dilate(oval, 1)
        keep = np.zeros(n + 1, dtype=bool)
        keep[comp[seed]] = True
        keep[0] = False
        labels[keep[comp]] = PART_INDEX["skin"]

    def refine(self, image: np.ndarray, labels: np.ndarray, lm: np.ndarray, rows: np.ndarray, cols: np.ndarray,
               h: float, w: float, jaw: float, real: np.ndarray | None = None) -> None:
        """The colour rules of the module docstring, in place on ``labels`` (neck by skin colour, hat by a colour
        unlike the hair beside the face); ``real``: bool mask of the crop pixels inside the photo (None: all)."""
        from scipy import ndimage

        skin = labels == PART_INDEX["skin"]
        if skin.sum() < 50:
            return
        # CIELAB of only the pixels a rule reads (skin, the neck zone, the hair): the whole crop cost ~3 ms.
        ref = np.median(rgb2lab(image[skin]), axis=0)
        chin = lm[CHIN]
        # Neck: skin-coloured person pixels below the jaw line, connected to the strip under the chin.
        below = (labels == PART_INDEX["neck"]) | (labels == PART_INDEX["clothes"])
        zone = (below & (rows < chin[1] + self.neck_max_depth * h)
                & (np.abs(cols - chin[0]) < self.neck_max_halfwidth * w))
        lab = rgb2lab(image[zone])
        skinlike = np.zeros_like(zone)
        skinlike[zone] = ((np.hypot(lab[:, 1] - ref[1], lab[:, 2] - ref[2]) < self.skin_chroma)
                          & (lab[:, 0] > ref[0] - self.skin_dark))
        skinlike = opening(skinlike, 1)
        comp, n = ndimage.label(skinlike)
        seed = skinlike & (rows < chin[1] + 0.15 * h) & (np.abs(cols - chin[0]) < 0.25 * w)
        keep = np.zeros(n + 1, dtype=bool)
        keep[comp[seed]] = True
        keep[0] = False
        neck = keep[comp]
        if neck.sum() > 0.02 * h * w:
            neck = closing(neck, 2) & below
            labels[below] = PART_INDEX["clothes"]
            labels[neck] = PART_INDEX["neck"]
        self.forehead(image, labels, lm, rows, cols, h, w, ref, rgb2lab, real)
        # Hat: hair above the forehead unlike the hair beside the face.
        hair = labels == PART_INDEX["hair"]
        eyes_y = 0.5 * (lm[33, 1] + lm[263, 1])
        xs = lm[:, 0]
        beside = hair & (rows > eyes_y) & (rows < jaw) & (((cols < xs.min()) & (cols > xs.min() - 0.35 * w))
                                                         | ((cols > xs.max()) & (cols < xs.max() + 0.35 * w)))
        top = hair & (rows < lm[FOREHEAD, 1])
        if real is not None:  # a hat is only what the photo shows: a reflected forehead is not one
            beside, top = beside & real, top & real
        if beside.sum() < 30 or top.sum() < 30:
            return
        hair_ref = np.median(rgb2lab(image[beside]), axis=0)
        # Unlike in hue (a cap, a hood) or far in lightness (a black cap over grey hair); highlights in the hair
        # differ in lightness only moderately.
        lab = rgb2lab(image[top])
        unlike = np.zeros_like(top)
        unlike[top] = ((np.hypot(lab[:, 1] - hair_ref[1], lab[:, 2] - hair_ref[2]) > self.hat_chroma)
                       | (np.abs(lab[:, 0] - hair_ref[0]) > self.hat_lightness))
        unlike = opening(unlike, 2)
        if unlike.sum() >= self.hat_min_share * top.sum():
            comp, n = ndimage.label(unlike)
            keep = []
            for i, sl in enumerate(ndimage.find_objects(comp), start=1):
                area = (comp[sl] == i).sum()
                bw, bh = sl[1].stop - sl[1].start, sl[0].stop - sl[0].start
                # A hat is one solid band across the head: wide, filling its box (hair highlights are streaks).
                if area >= 0.05 * top.sum() and bw >= self.hat_min_width * w and area >= 0.5 * bw * bh:
                    keep.append(i)
            if keep:
                hat = closing(np.isin(comp, keep), 2) & hair
                labels[hat if real is None else hat & real] = PART_INDEX["hat"]
