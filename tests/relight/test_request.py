"""A relight request: its checks (Request.from_config) and its target for a source (Target.for_source)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from omegaconf import OmegaConf

from difareli.errors import UserError
from difareli.lighting import sh
from difareli.relight.request import Request, Target
from difareli.utils.viz import video_format

LIGHT = np.zeros((9, 3))
LIGHT[0], LIGHT[2] = 1.0, 0.5  # an ambient and a light from the front-ish


class FakeRelighter:
    """What Target.for_source asks a relighter: a source's key sun (a fixed direction) and a store record."""

    def __init__(self, direction):
        self.direction, self.asked = np.asarray(direction, np.float64), []

    def key_sun(self, source):
        self.asked.append(source.what)
        return SimpleNamespace(direction=self.direction)

    def source(self, store, rid):
        return SimpleNamespace(arrays=store.read(rid, ["light", "shadow"]), what=rid)


class FakeStore:
    def read(self, rid, names):
        other = LIGHT.copy()
        other[1] = 0.3
        return {"light": other, "shadow": np.array([2.5])}


def src():
    return SimpleNamespace(arrays={"light": LIGHT}, what="the source")


def test_a_yaw_turns_the_sources_key_sun_with_its_light():
    d = np.array([0.6, 0.0, 0.8])
    rel = FakeRelighter(d)
    targets, found = Target(yaw=90.0).for_source(rel, src())
    assert np.allclose(targets.suns[0], sh.rotation_yaw(90.0) @ d)
    assert not np.allclose(targets.suns[0], d)
    assert np.allclose(targets.lights[0], sh.yaw(LIGHT, 90.0))
    assert rel.asked == ["the source"] and np.allclose(found.direction, d)
    targets, _ = Target(roll=-30.0).for_source(rel, src())
    assert np.allclose(targets.suns[0], sh.rotation_roll(-30.0) @ d)


def test_a_target_record_gives_its_light_shadow_and_sun():
    d = np.array([0.0, 0.6, 0.8])
    rel = FakeRelighter(d)
    target = Target(record="s1_l2")
    targets, _ = target.for_source(rel, src(), rel.source(FakeStore(), target.record))
    assert rel.asked == ["s1_l2"]  # the sun of the image whose light it is: the record's, not the source's
    assert np.allclose(targets.suns[0], d) and targets.shadows == (2.5,)
    assert np.allclose(targets.lights[0][1], 0.3)
    target = Target(record="s1_l2", shadow=-1.0)
    targets, _ = target.for_source(rel, src(), rel.source(FakeStore(), target.record))
    assert targets.shadows == (-1.0,)  # a given c' wins over the record's
    with pytest.raises(ValueError, match="pass its source"):
        target.for_source(rel, src())  # a record target without its record read


def test_peak_and_light_files_keep_the_radiance_peak(tmp_path):
    rel = FakeRelighter([0.0, 0.0, 1.0])
    targets, found = Target(yaw=45.0, sun="peak").for_source(rel, src())
    assert found is None and targets.suns == (None,) and rel.asked == []
    path = tmp_path / "light.npy"
    np.save(path, LIGHT)
    targets, found = Target(light=str(path)).for_source(rel, src())
    assert found is None and rel.asked == [] and np.allclose(targets.lights[0], LIGHT)


def cfg(**over):
    base = {"store": None, "record": None, "versions": None, "image": None, "face": "largest", "photo_size": None,
            "strict": False, "video": {"axis": None, "frames": 8, "fps": 20, "format": "gif"}, "out_dir": "out",
            "target": {"light": None, "record": None, "yaw": None, "roll": None, "envmap": None, "shadow": None,
                       "sun": "shadows"},
            "composite": {"mode": "ratio", "feather": 0.03, "parts": None}, "checkpoint": "difareli_pp-synth64",
            "sampler": {"preset": "default"}, "runtime": {"precision": "fp32"}, "mean_matching": True,
            "batch_size": 4, "progress": False}
    return OmegaConf.merge(base, OmegaConf.from_dotlist([f"{k}={v}" for k, v in over.items()]))


@pytest.fixture
def store(tmp_path):
    """A store of one record (its light only): what the request's store check opens."""
    from difareli.data.store import EncodingStore

    st = EncodingStore.create(tmp_path / "store", {}, ["light"], durable=False)
    st.write("s1_l0", {"light": LIGHT.astype(np.float32)})
    return str(st.root)


def test_a_request_is_checked_once_naming_the_key(store, tmp_path):
    r = Request.from_config(cfg(store=store, **{"target.yaw": 30}))
    assert r.target == Target(yaw=30.0) and str(r.store.root) == store and r.video_axis is None  # opened once
    with pytest.raises(UserError, match="either store=.* or image="):
        Request.from_config(cfg(**{"target.yaw": 30}))
    with pytest.raises(UserError, match="either store=.* or image="):
        Request.from_config(cfg(store=store, image="p.png", **{"target.yaw": 30}))
    with pytest.raises(UserError, match="target.record=r1 names a store record"):
        Request.from_config(cfg(image="p.png", **{"target.record": "r1"}))
    with pytest.raises(UserError, match="nothing to do"):
        Request.from_config(cfg(store=store))
    with pytest.raises(UserError, match="target.light"):
        Request.from_config(cfg(store=store, **{"target.light": "/no/such/light.npy"}))
    assert Request.from_config(cfg(store=store, **{"video.axis": "roll"})).video_frames == 8
    # The store opens and holds the records named, before any work (the key named as the config spells it).
    with pytest.raises(UserError, match="no encoding store at"):
        Request.from_config(cfg(store=tmp_path / "nowhere", **{"target.yaw": 30}))
    assert Request.from_config(cfg(store=store, record="s1_l0", **{"target.record": "s1_l0"})).record == "s1_l0"
    for key in ("record", "target.record"):
        with pytest.raises(UserError, match=rf"^{key}=s9_l0: no such record in the store .* \(1 records, e.g. "
                                            r"s1_l0\); give one of its record ids"):
            Request.from_config(cfg(store=store, **{key: "s9_l0", "target.yaw": 30}))
    with pytest.raises(UserError, match="versions.shadow_map='v9'"):
        Request.from_config(cfg(store=store, **{"versions.shadow_map": "v9", "target.yaw": 30}))
    # Where the answer goes, checked and resolved once (the command writes with these values).
    r = Request.from_config(cfg(store=store, out_dir="somewhere", **{"video.axis": "yaw", "video.format": "auto",
                                                                      "video.fps": 12}))
    assert (r.out_dir, r.video_fps, r.video_format) == ("somewhere", 12, video_format("auto"))
    with pytest.raises(UserError, match="video.fps=0 is invalid"):
        Request.from_config(cfg(store=store, **{"video.axis": "yaw", "video.fps": 0}))
    with pytest.raises(UserError, match="out_dir is empty"):
        Request.from_config(cfg(store=store, out_dir="", **{"video.axis": "yaw"}))
    for key in ("yaw", "roll"):  # the one check of a turn (target_lights turns what it is given)
        c = cfg(store=store)
        c.target[key] = float("nan")
        with pytest.raises(UserError, match=f"target.{key}=nan is invalid"):
            Request.from_config(c)


def test_how_a_request_is_relit_is_checked_with_it(store):
    """The sampler (whole, by its spec), the runtime and the batch size are the request's values (``how``, a
    Relighting), checked by from_config before any work and handed to the relighter as typed values."""
    from difareli.diffusion.spec import PRESETS, SamplerSpec
    from difareli.runtime.core import Runtime

    r = Request.from_config(cfg(store=store, **{"target.yaw": 30, "sampler.steps": 7})).how
    assert r.sampler == SamplerSpec.preset("default", steps=7) and r.sampler != PRESETS["default"]
    assert r.runtime == Runtime(precision="fp32") and (r.batch_size, r.mean_matching, r.progress) == (4, True, False)
    assert r.checkpoint == "difareli_pp-synth64"
    assert Request.from_config(cfg(store=store, sampler="null", **{"target.yaw": 30})).how.sampler is None
    for override, want in {"sampler.name": ("euler", "unknown sampler 'euler'"),
                           "sampler.steps": (0, "steps must be an integer >= 1"),
                           "runtime.precision": ("fp8", "runtime.precision='fp8' is not one of"),
                           "batch_size": (0, "batch_size=0 is invalid"),
                           "sampler": ("fast", "sampler='fast' is not a sampler config: give a mapping")}.items():
        value, message = want
        with pytest.raises(UserError, match=message):
            Request.from_config(cfg(store=store, **{override: value, "target.yaw": 30}))


def test_the_key_sun_is_found_once_per_source_key(monkeypatch):
    # A request with a yaw target and a video of the source's own light asks for its key sun twice: fitted once.
    from difareli.relight.relighter import Relighter
    from difareli.render import sun_fit

    calls = []
    monkeypatch.setattr(sun_fit, "key_sun", lambda arrays, light: calls.append(1) or SimpleNamespace(direction=1))
    me = SimpleNamespace(model_inputs=["shading", "shadow_map"], _suns={})
    keyed = SimpleNamespace(arrays={"light": LIGHT}, key=("store", "r1"))
    assert Relighter.key_sun(me, keyed) is Relighter.key_sun(me, keyed) and len(calls) == 1
    other = SimpleNamespace(arrays={"light": LIGHT}, key=("store", "r2"))
    Relighter.key_sun(me, other)
    anonymous = SimpleNamespace(arrays={"light": LIGHT}, key=None)  # not cached: nothing names it
    Relighter.key_sun(me, anonymous)
    Relighter.key_sun(me, anonymous)
    assert len(calls) == 4
    assert Relighter.key_sun(SimpleNamespace(model_inputs=["shading"], _suns={}), keyed) is None


def test_a_plausible_rotation_makes_each_frames_light_plausible_for_the_face():
    """Rotation(plausible=True), the demo's rotation: the same frames, each light through presets.plausible (a
    strongly directional light turned is negative on much of the sphere; made plausible, it is not)."""
    from difareli.lighting import presets
    from difareli.relight.request import Rotation

    light = np.zeros((9, 3))
    light[0], light[3] = 0.2, 1.0  # little ambient, a strong first-order term: negative on the far side
    rel = SimpleNamespace(model_inputs=[], key_sun=lambda s: None)
    source = SimpleNamespace(arrays={"light": light}, what="the source")
    plain, _ = Rotation("yaw", 8).for_source(rel, source)
    made, _ = Rotation("yaw", 8, plausible=True).for_source(rel, source)
    assert np.allclose(made.lights, [presets.plausible(x, light, None) for x in plain.lights])
    assert not np.allclose(made.lights, plain.lights) and made.shadows == plain.shadows
