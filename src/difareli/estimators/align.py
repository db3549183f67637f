"""Face detection and FFHQ-style alignment (mediapipe 0.10.21 legacy solutions; models ship in the wheel).

1. BlazeFace (``face_detection``) on a copy shrunk to ``detect_max_side``: the short-range model (0, faces
   within ~2 m: portraits) first, the full-range model (1) only if it finds nothing; the largest box wins
   and the face count is recorded (several faces are a note, not a failure).
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


def warp_quad(image: np.ndarray, quad: np.ndarray, size: int) -> np.ndarray:
    """Resample the oriented square ``quad`` of ``image`` to ``size`` x ``size`` (bilinear, reflect pad)."""
    import cv2

    quad = np.asarray(quad, dtype=np.float64)
    side = np.hypot(*(quad[3] - quad[0]))
    shrink = int(np.floor(side / size * 0.5))
    if shrink > 1:  # area-average first, as FFHQ does, so downscaling does not alias
        h, w = image.shape[:2]
        image = cv2.resize(image, (max(1, round(w / shrink)), max(1, round(h / shrink))), interpolation=cv2.INTER_AREA)
        quad = quad * [image.shape[1] / w, image.shape[0] / h]
    ex = (quad[3] - quad[0]) / size  # input step per output column
    ey = (quad[1] - quad[0]) / size  # input step per output row
    # Output pixel centre (u + .5, v + .5) -> input continuous coords; cv2 indexes pixel centres as integers.
    off = quad[0] + 0.5 * (ex + ey) - 0.5
    m = np.array([[ex[0], ey[0], off[0]], [ex[1], ey[1], off[1]]])
    return cv2.warpAffine(image, m, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REFLECT_101)


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
                 models: tuple[int, ...] = (0, 1), crop_factor: float = 2.2, mesh_crop: int = 384):
        self.size = int(size)
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
        import mediapipe as mp

        h, w = rgb.shape[:2]
        f = min(1.0, self.detect_max_side / max(h, w))
        small = rgb if f == 1.0 else cv2.resize(rgb, (round(w * f), round(h * f)), interpolation=cv2.INTER_AREA)
        small = np.ascontiguousarray(small)
        for model in self.models:
            if model not in self._detectors:
                self._detectors[model] = mp.solutions.face_detection.FaceDetection(
                    model_selection=model, min_detection_confidence=self.min_detection_confidence)
            res = self._detectors[model].process(small)
            boxes = []
            for d in res.detections or []:
                b = d.location_data.relative_bounding_box
                boxes.append((float(d.score[0]), np.array([b.xmin * w, b.ymin * h, b.width * w, b.height * h])))
            if boxes:
                return sorted(boxes, key=lambda sb: -sb[1][2] * sb[1][3])
        return []

    def landmarks(self, rgb: np.ndarray, box: np.ndarray | None) -> np.ndarray | None:
        """FaceMesh landmarks (478, 3) in original pixels, from a square crop around ``box`` (or the image)."""
        if box is None:
            found = self.mesh(rgb)
            return found[0] if found else None
        cx, cy = box[0] + box[2] / 2, box[1] + box[3] / 2
        half = self.crop_factor * max(box[2], box[3]) / 2
        quad = np.array([[cx - half, cy - half], [cx - half, cy + half], [cx + half, cy + half], [cx + half, cy - half]])
        found = self.mesh(warp_quad(rgb, quad, self.mesh_crop))
        if not found:
            return None
        lm = found[0]
        scale = 2 * half / self.mesh_crop
        return np.concatenate([lm[:, :2] * scale + quad[0], lm[:, 2:] * scale], axis=1)

    def __call__(self, rgb: np.ndarray) -> dict:
        """``{"image": aligned uint8, "quad": (4, 2), "faces": n, "box": ..., "notes": [...], "landmarks": (478, 3)
        FaceMesh landmarks in original pixels}``."""
        faces = self.detect(rgb)
        notes = []
        box = faces[0][1] if faces else None
        if len(faces) > 1:
            notes.append(f"{len(faces)} faces detected; kept the largest (box x,y,w,h = "
                         f"{', '.join(f'{v:.0f}' for v in box)})")
        lm = self.landmarks(rgb, box)
        if lm is None and box is not None:
            lm = self.landmarks(rgb, None)  # detector box was off: let FaceMesh search the whole photo
        if lm is None:
            raise BadInput("no face detected" if not faces else "face detected but FaceMesh found no landmarks")
        quad = ffhq_quad(lm[:, :2])
        return {"image": warp_quad(rgb, quad, self.size), "quad": quad, "faces": max(len(faces), 1),
                "box": None if box is None else box.tolist(), "notes": notes, "landmarks": lm}
