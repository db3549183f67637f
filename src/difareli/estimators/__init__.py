"""Estimators of difareli-preprocess: real face photos -> the encodings of SPEC 2, offline.

Modules: ``loading`` (defensive decoding), ``align`` (BlazeFace + FaceMesh, FFHQ crop), ``geometry``
(FaceMesh surface -> shape, cam, normal, depth), ``masks`` (FaceMesh outlines + selfie segmentation),
``light`` (SH fit on skin, shading reference), ``identity`` (dlib descriptor), ``shadow`` (classifier logit
c, ray-traced shadow map), ``pipeline`` (dependency planning, store writes, report), ``preview``,
``quiet`` (mediapipe's native log noise and the pkg_resources warning silenced, nothing else).
Each estimator is a Hydra component in ``conf/preprocess/<role>/``. Needs mediapipe 0.10.21 (numpy < 2)
and face_recognition; imported lazily so that this package imports without them.
"""
