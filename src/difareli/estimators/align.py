"""Face detection and FFHQ-style alignment (mediapipe 0.10.21 legacy solutions; models ship in the wheel).

1. BlazeFace (``face_detection``) on a copy shrunk to ``detect_max_side``: the short-range model (0, faces
   within ~2 m: portraits) first, the full-range model (1) only if it finds nothing; on a photo of at least
   ``tile_min_side`` px the short-range model also runs on overlapping square tiles (its 128 px input misses
   faces under ~1/6 of the photo: 3 of the 6 faces of a group photo were found without tiles, 6 with), and
   boxes covering the same face are merged. The largest box wins unless ``select`` names one (a box of
   :meth:`FaceAligner.detect`); the face count is recorded (several faces are a note, not a failure).
2. FaceMesh on a square crop around that box gives 478 landmarks in the original image.
3. The FFHQ recipe (Karras et al., ``ffhq-dataset/download_ffhq.py``) turns the eye centres and the mouth
   corners into an oriented square ``quad``, which is resampled to ``size`` x ``size`` (reflect padding
   where it leaves the photo; FFHQ additionally blurs the padding, which we skip).

Coordinates are continuous pixel coordinates (``x`` right, ``y`` down, pixel ``i`` spans ``[i, i+1)``), the
convention of mediapipe's normalised landmarks times the image size and of ``OrthoCamera.project``.
"""

from __future__ import annotations

import numpy as np

from .loading import BadInput

# FaceMesh indices. "Left"/"right" are the subject's (mediapipe and MASK_PARTS agree): the subject's
# right eye is on the image left, which FFHQ calls ``eye_left``.
MOUTH_CORNERS = (61, 291)  # image left, image right


def eye_indices(side: str) -> np.ndarray:
    """Vertex indices of the subject's ``"left"`` or ``"right"`` eye contour (FACEMESH_*_EYE)."""
    from mediapipe.python.solutions import face_mesh_connections as fmc

    edges = fmc.FACEMESH_LEFT_EYE if side == "left" else fmc.FACEMESH_RIGHT_EYE
    return np.array(sorted({i for e in edges for i in e}))


def ffhq_quad(landmarks_xy: np.ndarray) -> np.ndarray:
    """FFHQ crop quad (4, 2): top-left, bottom-left, bottom-right, top-right, from FaceMesh landmarks (N, 2)."""
    lm = np.asarray(landmarks_xy, dtype=np.float64)
    eye_left = lm[eye_indices("right")].mean(0)   # image left
    eye_right = lm[eye_indices("left")].mean(0)
    eye_avg = (eye_left + eye_right) * 0.5
    eye_to_eye = eye_right - eye_left
    mouth_avg = (lm[MOUTH_CORNERS[0]] + lm[MOUTH_CORNERS[1]]) * 0.5
    eye_to_mouth = mouth_avg - eye_avg
    x = eye_to_eye - np.flipud(eye_to_mouth) * [-1, 1]
    x /= np.hypot(*x)
    x *= max(np.hypot(*eye_to_eye) * 2.0, np.hypot(*eye_to_mouth) * 1.8)
    y = np.flipud(x) * [-1, 1]
    c = eye_avg + eye_to_mouth * 0.1
    return np.stack([c - x - y, c - x + y, c + x + y, c + x - y])


def warp_quad(image: np.ndarray, quad: np.ndarray, size: int, border: str = "reflect") -> np.ndarray:
    """Resample the oriented square ``quad`` of ``image`` to ``size`` x ``size`` (bilinear; where the quad leaves
    the image: ``border`` reflect | replicate | zeros)."""
    import cv2

    quad = np.asarray(quad, dtype=np.float64)
    side = np.hypot(*(quad[3] - quad[0]))
    shrink = int(np.floor(side / size * 0.5))
    if shrink > 1:  # area-average first, as FFHQ does, so downscaling does not alias
        h, w = image.shape[:2]
        image = cv2.resize(image, (max(1, round(w / shrink)), max(1, round(h / shrink))), interpolation=cv2.INTER_AREA)
        quad = quad * [image.shape[1] / w, image.shape[0] / h]
    m = crop_to_photo(quad, size)
    mode = {"reflect": cv2.BORDER_REFLECT_101, "replicate": cv2.BORDER_REPLICATE, "zeros": cv2.BORDER_CONSTANT}
    return cv2.warpAffine(image, m, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=mode[border], borderValue=0)


def inside_photo(quad: np.ndarray, size: int, hw: tuple[int, int]) -> np.ndarray:
    """Bool (size, size): crop pixels whose centre samples the photo (``hw``) rather than its padding."""
    quad = np.asarray(quad, dtype=np.float64)
    t = np.arange(size, dtype=np.float64) + 0.5  # pixel centres
    # q0 + u (q3 - q0) / size + v (q1 - q0) / size, the same operations in the same order as on a full (size, size, 2)
    # grid (bit for bit), on a row of columns and a column of rows that broadcast: ~80x faster at 256 px.
    xy_u = quad[0] + t[:, None] * (quad[3] - quad[0]) / size  # (size, 2): the column term
    x = xy_u[None, :, 0] + t[:, None] * (quad[1, 0] - quad[0, 0]) / size
    y = xy_u[None, :, 1] + t[:, None] * (quad[1, 1] - quad[0, 1]) / size
    return (x >= 0) & (x <= hw[1]) & (y >= 0) & (y <= hw[0])


def crop_to_photo(quad: np.ndarray, size: int) -> np.ndarray:
    """The (2, 3) affine from crop pixel indices to photo pixel indices (the one :func:`warp_quad` samples)."""
    quad = np.asarray(quad, dtype=np.float64)
    ex, ey = (quad[3] - quad[0]) / size, (quad[1] - quad[0]) / size  # photo steps per crop column and row
    off = quad[0] + 0.5 * (ex + ey) - 0.5  # pixel centres: index i sits at continuous i + 0.5 (cv2: at i)
    return np.array([[ex[0], ey[0], off[0]], [ex[1], ey[1], off[1]]])


def photo_window(quad: np.ndarray, hw: tuple[int, int]) -> tuple[int, int, int, int] | None:
    """``(y0, y1, x0, x1)``: the photo pixels the quad touches, clipped to the photo; None if it misses it."""
    quad = np.asarray(quad, dtype=np.float64)
    x0, y0 = np.floor(quad.min(0)).astype(int) - 1
    x1, y1 = np.ceil(quad.max(0)).astype(int) + 1
    y0, x0, y1, x1 = max(y0, 0), max(x0, 0), min(y1, hw[0]), min(x1, hw[1])
    return None if y1 <= y0 or x1 <= x0 else (int(y0), int(y1), int(x0), int(x1))


def merge_boxes(found: list[tuple[float, np.ndarray]], overlap: float = 0.5) -> list[tuple[float, np.ndarray]]:
    """Boxes (score, x0 y0 w h) less those whose intersection covers ``overlap`` of the smaller of two boxes
    (the same face seen in two tiles, or in a tile and the whole photo); the higher score stays."""
    kept: list[tuple[float, np.ndarray]] = []
    for score, b in sorted(found, key=lambda sb: -sb[0]):
        dup = False
        for _, k in kept:
            iw = min(b[0] + b[2], k[0] + k[2]) - max(b[0], k[0])
            ih = min(b[1] + b[3], k[1] + k[3]) - max(b[1], k[1])
            if iw > 0 and ih > 0 and iw * ih >= overlap * min(b[2] * b[3], k[2] * k[3]):
                dup = True
                break
        if not dup:
            kept.append((score, b))
    return kept


#: A box with more than this share of its area outside the photo is a face only if FaceMesh confirms it (a box
#: running 28 px past a sports photo's edge over a blurred crowd was the "largest face" and no face at all).
PAST_EDGE = 0.05


def clip_box(box: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, float]:
    """``box`` (x0, y0, w, h) clipped to a photo of ``shape`` (h, w), and the share of its area inside the photo."""
    x0, y0 = max(box[0], 0.0), max(box[1], 0.0)
    x1, y1 = min(box[0] + box[2], shape[1]), min(box[1] + box[3], shape[0])
    inside = max(x1 - x0, 0.0) * max(y1 - y0, 0.0)
    return np.array([x0, y0, max(x1 - x0, 0.0), max(y1 - y0, 0.0)]), inside / max(box[2] * box[3], 1e-12)


def inside_boxes(found: list[tuple[float, np.ndarray]], shape: tuple[int, int], confirmed
                 ) -> list[tuple[float, np.ndarray]]:
    """Detections clipped to the photo: a box with more than :data:`PAST_EDGE` of it outside is kept (clipped) only
    where ``confirmed(clipped box)`` (FaceMesh finds a face there), so that the largest box is a real face."""
    out = []
    for score, box in found:
        clipped, share = clip_box(np.asarray(box, np.float64), shape)
        if clipped[2] * clipped[3] > 0 and (share >= 1.0 - PAST_EDGE or confirmed(clipped)):
            out.append((score, clipped))
    return out


def quad_to_crop(points_xy: np.ndarray, quad: np.ndarray, size: int) -> np.ndarray:
    """Map original-image points (N, 2) into the aligned crop's pixel coordinates."""
    quad = np.asarray(quad, dtype=np.float64)
    basis = np.stack([(quad[3] - quad[0]) / size, (quad[1] - quad[0]) / size], axis=1)  # columns ex, ey
    return (np.asarray(points_xy, dtype=np.float64) - quad[0]) @ np.linalg.inv(basis).T


def landmarks_to_crop(landmarks: np.ndarray, quad: np.ndarray, size: int) -> np.ndarray:
    """FaceMesh landmarks (N, 3) in original pixels -> the aligned crop's: x, y through :func:`quad_to_crop`,
    z scaled like them (the quad is a similarity, and FaceMesh's z shares x's unit)."""
    lm = np.asarray(landmarks, dtype=np.float64)
    quad = np.asarray(quad, dtype=np.float64)
    return np.c_[quad_to_crop(lm[:, :2], quad, size), lm[:, 2] * size / np.hypot(*(quad[3] - quad[0]))]


class FaceMeshRunner:
    """Lazily built mediapipe FaceMesh (static images, refined landmarks); returns (478, 3) pixel landmarks."""

    def __init__(self, min_detection_confidence: float = 0.5, max_num_faces: int = 1):
        self.min_detection_confidence = min_detection_confidence
        self.max_num_faces = max_num_faces
        self._mesh = None

    def __call__(self, rgb: np.ndarray) -> list[np.ndarray]:
        """Landmarks of each face found, ``(478, 3)``: x, y in pixels, z (mediapipe's relative depth,
        smaller = nearer the camera) scaled by the image width like x."""
        if self._mesh is None:
            import mediapipe as mp

            self._mesh = mp.solutions.face_mesh.FaceMesh(
                static_image_mode=True, max_num_faces=self.max_num_faces, refine_landmarks=True,
                min_detection_confidence=self.min_detection_confidence)
        h, w = rgb.shape[:2]
        res = self._mesh.process(np.ascontiguousarray(rgb))
        out = []
        for face in res.multi_face_landmarks or []:
            lm = np.array([(p.x, p.y, p.z) for p in face.landmark], dtype=np.float64)
            out.append(lm * [w, h, w])
        return out


class FaceAligner:
    """Detect the largest face and return the FFHQ-aligned ``size`` x ``size`` crop (see module doc)."""

    def __init__(self, size: int = 256, detect_max_side: int = 1024, min_detection_confidence: float = 0.5,
                 models: tuple[int, ...] = (0, 1), crop_factor: float = 2.2, mesh_crop: int = 384,
                 tile_min_side: int = 384, tile_share: float = 0.6, border: str = "reflect"):
        self.size = int(size)
        self.tile_min_side, self.tile_share, self.border = int(tile_min_side), float(tile_share), border
        self.select: np.ndarray | None = None  # a box of detect() to align instead of the largest
        self.detect_max_side = detect_max_side
        self.min_detection_confidence = min_detection_confidence
        self.models = tuple(models)
        self.crop_factor = crop_factor
        self.mesh_crop = mesh_crop
        self._detectors: dict[int, object] = {}
        self.mesh = FaceMeshRunner(min_detection_confidence)

    def detect(self, rgb: np.ndarray) -> list[tuple[float, np.ndarray]]:
        """(score, box x0, y0, w, h in original pixels) of every face, largest first; the detector models
        are tried in ``models`` order until one finds a face."""
        import cv2

        h, w = rgb.shape[:2]
        f = min(1.0, self.detect_max_side / max(h, w))
        small = rgb if f == 1.0 else cv2.resize(rgb, (round(w * f), round(h * f)), interpolation=cv2.INTER_AREA)
        small = np.ascontiguousarray(small)
        boxes: list[tuple[float, np.ndarray]] = []
        for model in self.models:
            boxes = self._run(model, small, 1.0 / f, (0, 0))
            if boxes:
                break
        sh, sw = small.shape[:2]
        if min(sh, sw) >= self.tile_min_side:  # small faces: the short-range model on overlapping tiles
            t = round(min(sh, sw) * self.tile_share)
            ys = np.unique(np.linspace(0, sh - t, max(2, int(np.ceil(2 * sh / t)) - 1)).round().astype(int))
            xs = np.unique(np.linspace(0, sw - t, max(2, int(np.ceil(2 * sw / t)) - 1)).round().astype(int))
            tiled = []
            for y0 in ys:
                for x0 in xs:
                    tiled += self._run(self.models[0], small[y0:y0 + t, x0:x0 + t], 1.0 / f, (x0, y0))
            merged = merge_boxes([(s + 1.0, b) for s, b in boxes] + tiled)  # the whole photo's boxes win
            # A face only a tile saw must also be one to FaceMesh (tiles see faces in shirts and patterns).
            boxes = [(s - 1.0, b) if s > 1.0 else (s, b) for s, b in merged
                     if s > 1.0 or self._confirmed(rgb, b)]
        boxes = inside_boxes(boxes, (h, w), lambda b: self._confirmed(rgb, b))
        return sorted(boxes, key=lambda sb: -sb[1][2] * sb[1][3])

    def _confirmed(self, rgb: np.ndarray, box: np.ndarray) -> bool:
        """FaceMesh finds a face whose landmarks' centre lies in ``box``."""
        lm = self.landmarks(rgb, box)
        if lm is None:
            return False
        cx, cy = lm[:, :2].mean(0)
        return bool(box[0] <= cx <= box[0] + box[2] and box[1] <= cy <= box[1] + box[3])

    def _run(self, model: int, rgb: np.ndarray, scale: float, offset: tuple[int, int]
             ) -> list[tuple[float, np.ndarray]]:
        """BlazeFace ``model`` on ``rgb`` (a tile at ``offset`` of the detection copy): boxes in photo pixels."""
        import mediapipe as mp

        if model not in self._detectors:
            self._detectors[model] = mp.solutions.face_detection.FaceDetection(
                model_selection=model, min_detection_confidence=self.min_detection_confidence)
        res = self._detectors[model].process(np.ascontiguousarray(rgb))
        h, w = rgb.shape[:2]
        out = []
        for d in res.detections or []:
            b = d.location_data.relative_bounding_box
            box = np.array([b.xmin * w + offset[0], b.ymin * h + offset[1], b.width * w, b.height * h]) * scale
            out.append((float(d.score[0]), box))
        return out

    def landmarks(self, rgb: np.ndarray, box: np.ndarray | None) -> np.ndarray | None:
        """FaceMesh landmarks (478, 3) in original pixels, from a square crop around ``box`` (or the image)."""
        if box is None:
            found = self.mesh(rgb)
            return found[0] if found else None
        cx, cy = box[0] + box[2] / 2, box[1] + box[3] / 2
        half = self.crop_factor * max(box[2], box[3]) / 2
        quad = np.array([[cx - half, cy - half], [cx - half, cy + half], [cx + half, cy + half],
                         [cx + half, cy - half]])
        found = self.mesh(warp_quad(rgb, quad, self.mesh_crop))
        if not found:
            return None
        lm = found[0]
        scale = 2 * half / self.mesh_crop
        return np.concatenate([lm[:, :2] * scale + quad[0], lm[:, 2:] * scale], axis=1)

    def __call__(self, rgb: np.ndarray) -> dict:
        """``{"image": aligned uint8, "quad": (4, 2), "faces": n, "box": ..., "notes": [...], "landmarks": (478, 3)
        FaceMesh landmarks in original pixels}``."""
        notes = []
        if self.select is not None:  # a face the caller chose among detect()'s (photo.py: face=<index>)
            faces, box = [(1.0, np.asarray(self.select, np.float64))], np.asarray(self.select, np.float64)
            lm = self.landmarks(rgb, box)
            if lm is not None:
                cx, cy = lm[:, :2].mean(0)
                if not (box[0] - 0.5 * box[2] <= cx <= box[0] + 1.5 * box[2]
                        and box[1] - 0.5 * box[3] <= cy <= box[1] + 1.5 * box[3]):
                    lm = None  # FaceMesh took a neighbouring face
        else:
            faces = self.detect(rgb)
            box = faces[0][1] if faces else None
            if len(faces) > 1:
                notes.append(f"{len(faces)} faces detected; kept the largest (box x,y,w,h = "
                             f"{', '.join(f'{v:.0f}' for v in box)}; face=<index>|all picks others)")
            lm = self.landmarks(rgb, box)
            if lm is None and box is not None:
                lm = self.landmarks(rgb, None)  # detector box was off: let FaceMesh search the whole photo
        if lm is None:
            raise BadInput("no face detected" if not faces else "face detected but FaceMesh found no landmarks")
        quad = ffhq_quad(lm[:, :2])
        return {"image": warp_quad(rgb, quad, self.size, self.border), "quad": quad, "faces": max(len(faces), 1),
                "box": None if box is None else box.tolist(), "notes": notes, "landmarks": lm}
