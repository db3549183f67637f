"""The single-shot student DiFaReli++_ss: pairs, training, resumable teacher pairs, one-pass relighting
through the relight CLI, the benchmark and bench-samplers."""

from __future__ import annotations

import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch.utils.data import default_collate

from difareli.utils import viz
from difareli.data.inputs import condition_tensors, image_to_tensor
from difareli.jobs.teacher_pairs import generate_teacher_pairs
from difareli.lit.pairs import SOURCE_KEY, pair_dataset
from difareli.relight.relightable import DiffusionRelightable, OnePassRelightable
from difareli.relight.relighter import Relighter
from difareli.data.store import EncodingStore
from difareli.errors import UserError
from difareli.render.retarget import render_shading, retarget
from difareli.relight.targets import Targets

from tests.helpers import compose_train, tiny_cpu_overrides

pytestmark = pytest.mark.usefixtures("one_thread")

SP, NS = ["shading", "shadow_map", "masks"], ["shape", "cam", "identity"]
SAMPLER = {"name": "ddim", "steps": 3}


def _student(dims, **kw):
    from difareli.lit.student import StudentModule

    return StudentModule(preset="tiny", input_dims=dims, **kw)


def _small_batch(store, kind, n=2):
    """``n`` pairs of the training split, average-pooled to 16 px (fast enough for a default test)."""
    ds = pair_dataset(kind, store, store.ids(split="train")[:n], SP, NS)
    batch = default_collate([ds[i] for i in range(n)])
    batch = {k: F.avg_pool2d(v, 2) if torch.is_tensor(v) and v.ndim == 4 else v for k, v in batch.items()}
    dims = {"spatial_channels": batch["spatial"].shape[1], "nonspatial_dim": batch["nonspatial"].shape[1],
            "resolution": 16}
    return batch, dims


def _fit(model, batch, steps=30, lr=2e-3):
    opt = torch.optim.Adam(model.parameters(), lr)
    losses = []
    for _ in range(steps):
        loss = model.loss(batch)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    return losses


def test_gt_pairs_are_same_subject_other_light_with_retargeted_maps(synth_store):
    store = EncodingStore.open(synth_store)
    torch.manual_seed(0)
    ds = pair_dataset("gt", store, store.ids(split="train"), SP, NS)
    for i in (0, 3):
        item, rid = ds[i], ds.ids[i]
        subject = store.meta(rid)["subject"]
        same = [o for o in store.ids(subject=subject) if o != rid
                and torch.equal(image_to_tensor(store.read(o, ["image"])["image"]), item["target_image"])]
        assert len(same) == 1  # the target image is another light index of the same subject
        src = {k: np.asarray(v) for k, v in store.read(rid).items()}
        light = np.asarray(store.read(same[0], ["light"])["light"])
        want = torch.from_numpy(render_shading(src, light)).permute(2, 0, 1)
        assert torch.allclose(item["target_spatial"][:3], want)  # shading re-rendered from the source's normals
        assert torch.equal(item["target_spatial"][4:], item["spatial"][4:])  # masks: the source's
        assert torch.equal(item["target_nonspatial"], item["nonspatial"])  # shape, cam, identity: the source's


def test_gt_pairs_with_stored_maps_take_the_target_records_own_map(synth_store):
    """``gt_maps=stored``: the target's shadow-map channel is the target record's stored map (the march's re-render
    otherwise), the shading still re-rendered; a bad value is one line naming the key."""
    store = EncodingStore.open(synth_store)
    ids = store.ids(split="train")
    torch.manual_seed(0)
    stored = pair_dataset("gt", store, ids, SP, NS, gt_maps="stored")
    torch.manual_seed(0)
    march = pair_dataset("gt", store, ids, SP, NS)
    differ = 0
    for i in range(6):
        torch.manual_seed(i)
        a = stored[i]
        torch.manual_seed(i)
        b = march[i]
        assert torch.equal(a["target_image"], b["target_image"])  # the same target drawn
        tid = next(o for o in store.ids(subject=store.meta(ids[i])["subject"])
                   if torch.equal(image_to_tensor(store.read(o, ["image"])["image"]), a["target_image"]))
        own = torch.from_numpy(np.asarray(store.read(tid, ["shadow_map"])["shadow_map"], np.float32))
        assert torch.allclose(a["target_spatial"][3], own.reshape(a["target_spatial"][3].shape))
        assert torch.equal(a["target_spatial"][:3], b["target_spatial"][:3])  # shading: re-rendered in both
        differ += not torch.equal(a["target_spatial"][3], b["target_spatial"][3])
    assert differ >= 1  # the stored maps are not the march's
    with pytest.raises(UserError, match="data.gt_maps='exact' is not one of"):
        pair_dataset("gt", store, ids, SP, NS, gt_maps="exact")


def test_shadow_pairs_take_a_records_cast_shadows_away_or_give_them_back(synth_store):
    """``data.pairs=gt_shadow``: ground-truth pairs plus a shadowed record under its own light, its cast shadows
    taken away (target: the same light rendered with no cast shadow, zero map) or given back (source: that image
    with a zero map); the light's shading is the same on both sides, so only the map changes."""
    store = EncodingStore.open(synth_store)
    ids = store.ids(split="train")
    ds = pair_dataset("gt_shadow", store, ids, SP, NS, gt_maps="stored")
    gt, shadow = ds.datasets
    assert len(ds.ids) == len(gt) + len(shadow) and set(shadow.ids) <= set(ids)
    rid = shadow.ids[0]
    rec = store.read(rid, ["image", "shadow_map", "image_unshadowed_gt"])
    assert np.asarray(rec["shadow_map"]).max() > 0
    image, free = image_to_tensor(rec["image"]), image_to_tensor(rec["image_unshadowed_gt"])
    assert not torch.equal(image, free)
    own = torch.from_numpy(np.asarray(rec["shadow_map"], np.float32))
    seen = set()
    for seed in range(12):
        torch.manual_seed(seed)
        item = shadow[0]
        away = torch.equal(item["target_image"], free)
        assert torch.equal(item["image"], image if away else free)
        assert torch.equal(item["target_image"], free if away else image)
        src_map, tgt_map = item["spatial"][3], item["target_spatial"][3]
        assert torch.allclose((src_map if away else tgt_map), own.reshape(src_map.shape))
        assert not (tgt_map if away else src_map).any()
        assert torch.equal(item["spatial"][:3], item["target_spatial"][:3])  # the same light's shading
        seen.add(away)
    assert seen == {True, False}


def test_gt_pairs_with_group_lights_take_the_light_of_a_face_of_the_group_under_the_same_light(synth_store):
    store = EncodingStore.open(synth_store)
    ids = store.ids(split="train")
    ds = pair_dataset("gt", store, ids, SP, NS, gt_light="group")
    rid = ids[0]
    src = {k: np.asarray(v) for k, v in store.read(rid).items()}
    torch.manual_seed(0)
    seen = set()
    for _ in range(24):
        item = ds[0]
        tid = next(o for o in ds.others[rid]
                   if torch.equal(image_to_tensor(store.read(o, ["image"])["image"]), item["target_image"]))
        key = (store.meta(tid)["light_group"], store.meta(tid)["light_index"])
        # Which record's fitted light re-rendered the target shading: one of the same group and light index.
        match = [o for o in ds.light_records[tid]
                 if torch.allclose(item["target_spatial"][:3], torch.from_numpy(
                     render_shading(src, np.asarray(store.read(o, ["light"])["light"]))).permute(2, 0, 1))]
        assert match and all((store.meta(o)["light_group"], store.meta(o)["light_index"]) == key for o in match)
        seen.update(store.meta(o)["subject"] for o in match)
    # Over 24 draws both faces of the group lent their fit (the chance of missing one is 2 * 0.5^24).
    assert len(seen) == 2
    with pytest.raises(Exception, match="gt_light"):
        pair_dataset("gt", store, ids, SP, NS, gt_light="everyone")


def test_gt_pairs_with_identity_include_the_source_under_its_own_light(synth_store):
    store = EncodingStore.open(synth_store)
    ids = store.ids(split="train")
    plain = pair_dataset("gt", store, ids, SP, NS)
    with_id = pair_dataset("gt", store, ids, SP, NS, gt_identity=True)
    for rid in ids[:4]:
        assert rid not in plain.others[rid]
        assert sorted(with_id.others[rid]) == sorted([rid, *plain.others[rid]])
    torch.manual_seed(0)
    i = ids.index(ids[0])
    own = image_to_tensor(store.read(ids[0], ["image"])["image"])
    # Two light indices per subject here: the identity pair comes up in half the draws.
    hits = sum(torch.equal(with_id[i]["target_image"], own) for _ in range(24))
    assert 4 <= hits <= 20


def test_identity_pairs_are_conditioned_on_the_source_s_own_light_even_with_group_lights(tmp_path):
    """gt_light=group lends another face's fit to a changed light; the identity pair (target = source) keeps the
    source's own fit, so that relit under its own light the input is what the student learns to return."""
    from difareli.synth.generator import generate

    # Estimated lights (v2): the two faces of a light group hold different fits of the same true light.
    generate(out_dir=str(tmp_path / "s"), subjects=4, lights=2, resolution=32, seed=0, realism="full",
             inputs="estimated_light")
    store = EncodingStore.open(tmp_path / "s")
    ids = store.ids()
    ds = pair_dataset("gt", store, ids, SP, NS, gt_light="group", gt_identity=True)
    rid = ids[0]
    fits = [np.asarray(store.read(o, ["light"])["light"]) for o in ds.light_records[rid]]
    assert len(fits) == 2 and np.abs(fits[0] - fits[1]).max() > 1e-3  # its group lends two different fits
    src = {k: np.asarray(v) for k, v in store.read(rid).items()}
    own_shading = torch.from_numpy(render_shading(src, src["light"])).permute(2, 0, 1)
    own = image_to_tensor(src["image"])
    torch.manual_seed(0)
    identity = [item for item in (ds[0] for _ in range(40)) if torch.equal(item["target_image"], own)]
    assert len(identity) >= 8  # half the draws with two light indices
    assert all(torch.allclose(item["target_spatial"][:3], own_shading) for item in identity)


def test_student_overfits_a_few_pairs(synth_store):
    """L2 on 2 fixed ground-truth pairs falls >= 3x in 30 Adam steps (measured on 4 pairs: 6.5x, 0.157 -> 0.024)."""
    torch.manual_seed(0)
    batch, dims = _small_batch(EncodingStore.open(synth_store), "gt")
    torch.manual_seed(0)
    losses = _fit(_student(dims), batch)
    assert np.isfinite(losses).all()
    assert losses[-1] < losses[0] / 3, losses[::5]


def test_shadow_weighted_l2_is_the_weighted_mean_inside_the_maps(synth_store):
    """shadow_weight w: the loss is mean((1 + w max(map_s, map_t)) d^2) / mean(1 + w max(...)) (computed by hand
    here); w = 0 and an empty map both give the plain MSE; a student without a map refuses a weight."""
    batch, dims = _small_batch(EncodingStore.open(synth_store), "gt")
    torch.manual_seed(0)
    plain = _student(dims).eval()
    torch.manual_seed(0)
    weighted = _student(dims, shadow_weight=4.0).eval()
    i = 3  # the default inputs: shading (3 channels), then the shadow map
    batch["target_spatial"][:, i] = 0.0
    batch["spatial"][:, i] = 0.0
    batch["target_spatial"][0, i, :8] = 1.0  # a map on the upper half of the first pair's target
    with torch.no_grad():
        a, b = plain.loss(batch), weighted.loss(batch)
        d2 = (plain.relight_once(batch["image"], plain.condition(batch["spatial"], batch["nonspatial"]),
                                 plain.condition(batch["target_spatial"], batch["target_nonspatial"]))
              - batch["target_image"]) ** 2
    w = 1.0 + 4.0 * batch["target_spatial"][:, i:i + 1]
    assert float(b["l2"]) == pytest.approx(float(a["loss"]), rel=1e-6)
    assert float(b["loss"]) == pytest.approx(float((w * d2).mean() / w.mean()), rel=1e-5)
    assert float(b["loss"]) != pytest.approx(float(a["loss"]), rel=1e-3)
    batch["target_spatial"][:, i] = 0.0
    with torch.no_grad():
        assert float(weighted.loss(batch)["loss"]) == pytest.approx(float(a["loss"]), rel=1e-6)
    from difareli.lit.student import StudentModule

    with pytest.raises(UserError, match="shadow_weight"):
        StudentModule(preset="tiny", input_dims={**dims, "spatial_channels": 3}, spatial_inputs=["shading"],
                      shadow_weight=1.0)


def test_residual_student_starts_as_the_identity(synth_store):
    # The UNet's output layer starts at zero, so input + network is exactly the input for any target.
    batch, dims = _small_batch(EncodingStore.open(synth_store), "gt")
    m = _student(dims).eval()
    out = m.relight_once(batch["image"], m.condition(batch["spatial"], batch["nonspatial"]),
                         m.condition(batch["target_spatial"], batch["target_nonspatial"]))
    assert torch.equal(out, batch["image"])


def test_identity_mapping_learned_from_identity_pairs(synth_store):
    """A direct (non-residual) student trained on identity pairs returns its input when source = target:
    error <= 10% of the untrained one (measured ~4%)."""
    batch, dims = _small_batch(EncodingStore.open(synth_store), "identity")
    assert torch.equal(batch["target_image"], batch["image"])
    torch.manual_seed(0)
    m = _student(dims, residual=False)

    def err():
        with torch.no_grad():
            c = m.condition(batch["spatial"], batch["nonspatial"])
            return float(F.mse_loss(m.relight_once(batch["image"], c, c), batch["image"]))

    before = err()
    _fit(m, batch)
    assert err() < 0.1 * before


# ------------------------------------------------------------------------------------------ teacher pairs
def _pairs(root):
    s = EncodingStore.open(root)
    return {p: (s.meta(p), {k: np.asarray(v) for k, v in s.read(p).items()}) for p in s.ids()}


def test_teacher_pairs_resume_after_kill(synth_store, tiny_checkpoint, tmp_path):
    store = EncodingStore.open(synth_store)
    relighter = Relighter(tiny_checkpoint("difareli_pp"), SAMPLER, device="cpu")
    full = generate_teacher_pairs(relighter, store, tmp_path / "full", limit=4, batch_size=3, progress=False)
    assert (full["written"], full["skipped"]) == (4, 0)
    # A killed run: 2 pairs written, and a half-written pair left in a scratch folder by a dead process.
    part = generate_teacher_pairs(relighter, store, tmp_path / "part", limit=4, batch_size=3, progress=False,
                                  stop_after=2)
    assert part["written"] == 2
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    scratch = tmp_path / "part" / "records" / f".tmp-{sorted(_pairs(tmp_path / 'full'))[-1]}-{int(dead.stdout)}"
    scratch.mkdir()
    (scratch / "image.npy").write_bytes(b"cut")
    from difareli.cli.teacher_pairs import run

    cfg = compose_train(tmp_path / "run", [f"checkpoint={tiny_checkpoint('difareli_pp')}", f"store={synth_store}",
                                           f"out={tmp_path / 'part'}", "limit=4", "batch_size=3", "progress=false",
                                           "sampler=ddim", "sampler.steps=3", "runtime.device=cpu"],
                      config_name="teacher_pairs")  # the relighter above: DDIM-3
    resumed = run(cfg)
    assert (resumed["written"], resumed["skipped"]) == (2, 2)
    assert not scratch.exists()
    a, b = _pairs(tmp_path / "full"), _pairs(tmp_path / "part")
    assert sorted(a) == sorted(b)
    for p in a:
        assert a[p][0] == b[p][0]  # same source, same target light record
        for k in a[p][1]:
            # Batches were composed differently (3 + 1 vs 2 + 2): float rounding may move a pixel by one level.
            assert np.abs(a[p][1][k].astype(np.float64) - b[p][1][k]).max() <= (1 if k == "image" else 1e-6), (p, k)
    # The batched relight equals the Relighter's one-image relight of the same source toward the same light (its
    # map marched toward the sun the pair's meta names).
    pid = sorted(a)[0]
    meta, arrays = a[pid]
    sun = np.asarray(meta["sun"])
    own = dict(relighter.source(store, meta[SOURCE_KEY]).arrays)
    one = relighter.relight(relighter.source_from_arrays(own),
                            Targets.of([arrays["light"]], [float(arrays["shadow"][0])], suns=[sun]))[0]
    assert np.abs(one.astype(int) - arrays["image"]).max() <= 1
    assert np.array_equal(arrays["shadow_map"], retarget(own, ["shadow_map"],
                                                         arrays["light"], float(arrays["shadow"][0]),
                                                         sun=sun)["shadow_map"])


# ------------------------------------------------------------------------------------------ the student's checkpoint
@pytest.fixture(scope="module")
def student_ckpt(synth_store, tmp_path_factory):
    """A student trained 3 steps by difareli-train model=student data.pairs=gt."""
    from difareli.cli.train import train

    out = tmp_path_factory.mktemp("student")
    cfg = compose_train(out, [
        *tiny_cpu_overrides(synth_store), "model=student", "data.pairs=gt",
        "trainer.max_steps=3", "trainer.val_check_interval=3", "trainer.limit_val_batches=1",
        "logger=[]", "callbacks.ema.decay=0.9",
    ])
    train(cfg)
    assert list((out / "grids").glob("relight_step*.png"))  # input | relit | target per validation pair
    return out / "checkpoints" / "last.ckpt"


def test_student_without_pairs_is_a_user_error(synth_store, tmp_path):
    from difareli.cli.train import train
    from difareli.errors import UserError

    cfg = compose_train(tmp_path, [f"data.root={synth_store}", "data.resolution=32", "data.synth=null",
                                   "data.num_workers=0", "model=student", "model.preset=tiny", "trainer=cpu",
                                   "trainer.max_steps=1", "sample_grid=false", "logger=[]"])
    with pytest.raises(UserError, match="data.pairs=gt"):
        train(cfg)


def test_student_checkpoint_loads_weights_only_as_one_pass(student_ckpt):
    from difareli.lit import load_checkpoint
    from difareli.lit.student import StudentModule

    ckpt = torch.load(student_ckpt, weights_only=True, map_location="cpu")
    assert ckpt["difareli_module"] == "difareli.lit.student.StudentModule"
    model = load_checkpoint(student_ckpt).model
    assert isinstance(model, StudentModule) and isinstance(model, OnePassRelightable)
    assert not isinstance(model, DiffusionRelightable)
    assert all(torch.equal(v, ckpt["state_dict"][k]) for k, v in model.state_dict().items())


def test_student_through_relight_cli(student_ckpt, synth_store, tmp_path):
    from difareli.cli.relight import run
    from difareli.lit import load_checkpoint

    store = EncodingStore.open(synth_store)
    rid = store.ids(split="test")[0]
    other = [o for o in store.ids(subject=store.meta(rid)["subject"]) if o != rid][0]
    cfg = compose_train(tmp_path, [f"checkpoint={student_ckpt}", f"store={synth_store}", f"record={rid}",
                                   f"target.record={other}", "video.axis=yaw", "video.frames=4", "video.format=gif",
                                   "progress=false",
                                   "runtime.device=cpu"], config_name="relight")
    written = run(cfg)
    relit = iio.imread(written["image"])[..., :3]
    # By hand: the source's encodings, the target's re-rendered toward the other record's light and c.
    model = load_checkpoint(student_ckpt).model
    src = {k: np.asarray(v) for k, v in store.read(rid).items()}
    o = store.read(other, ["light", "shadow"])
    tgt = retarget(src, SP + NS, np.asarray(o["light"]), float(o["shadow"][0]))
    with torch.no_grad():
        want = model.relight_once(image_to_tensor(src["image"])[None],
                                  model.condition(*condition_tensors(model, [src])),
                                  model.condition(*condition_tensors(model, [tgt])))[0]
    assert np.abs(relit.astype(int) - viz.to_uint8(want.clamp(-1, 1))).max() <= 1
    # A GIF merges identical consecutive frames (two lights from behind can both leave the face unlit): count the
    # frames by their total duration.
    from PIL import Image, ImageSequence

    with Image.open(written["video"]) as im:
        total_ms = sum(f.info["duration"] for f in ImageSequence.Iterator(im))
    assert total_ms == 4 * round(1000 / cfg.video.fps)


def test_student_through_benchmark_and_bench_samplers(student_ckpt, synth_store, tiny_checkpoint, tmp_path):
    from difareli.cli.bench_samplers import run as bench_samplers
    from difareli.cli.benchmark import run as benchmark

    res = benchmark(compose_train(tmp_path / "b", [f"store={synth_store}", "progress=false", "num_threads=null",
                                                   "method=diffusion", f"method.checkpoint={student_ckpt}",
                                                   "limit=2", "runtime.device=cpu"], config_name="benchmark"))
    assert {r.method for r in res.records} == {"student"}
    assert len(res.records) == 4 and all(r.status == "ok" and np.isfinite(r.mse) for r in res.records)
    out = bench_samplers(compose_train(tmp_path / "s", [
        f"checkpoint={tiny_checkpoint('difareli_pp')}", f"store={synth_store}", f"student={student_ckpt}",
        "steps=[2]", "names=[ddim]", "reference=null", "limit=1", "progress=false", "runtime.device=cpu"],
        config_name="bench_samplers"))
    rows = {r["sampler"]: r for r in out["rows"]}
    assert rows["student"]["nfe"] == 1 and np.isfinite(rows["student"]["gt/mse"])
    assert rows["ddim"]["speedup"] == pytest.approx(rows["ddim"]["time/seconds"] / rows["student"]["time/seconds"])
    # End to end, both sides pay the same target shadow map (the same record and target light).
    assert rows["ddim"]["time/targets"] > 0 and rows["student"]["time/targets"] > 0
    for r in rows.values():
        assert r["time/end_to_end"] == pytest.approx(r["time/seconds"] + r["time/targets"])
    assert rows["ddim"]["speedup/end_to_end"] == pytest.approx(
        rows["ddim"]["time/end_to_end"] / rows["student"]["time/end_to_end"])
    # The same maps added to both sides pull the ratio toward 1 (whichever side is faster at this toy size).
    s, e2e = rows["ddim"]["speedup"], rows["ddim"]["speedup/end_to_end"]
    assert min(1.0, s) < e2e < max(1.0, s)


def test_bench_samplers_refuses_a_student_as_the_swept_checkpoint(student_ckpt, synth_store, tmp_path):
    from difareli.errors import UserError
    from difareli.cli.bench_samplers import run as bench_samplers

    cfg = compose_train(tmp_path / "s", [f"checkpoint={student_ckpt}", f"store={synth_store}", "steps=[2,4]",
                                         "limit=1", "progress=false", "runtime.device=cpu"],
                        config_name="bench_samplers")
    with pytest.raises(UserError, match=r"one-pass student: it has no sampler .* student="):
        bench_samplers(cfg)
    assert not (tmp_path / "s" / "bench_samplers.csv").exists()


def test_bench_samplers_checks_the_student_before_the_teacher_rows(synth_store, tiny_checkpoint, tmp_path,
                                                                   monkeypatch):
    """A wrong student= fails in seconds, not after the teacher's DDIM-1000 rows; a shipped name is loaded."""
    from difareli.perf import samplers as speed
    from difareli.cli.bench_samplers import run as bench_samplers

    class TeacherRowsStarted(Exception):
        pass

    def teacher_rows(*args, **kwargs):
        raise TeacherRowsStarted

    monkeypatch.setattr(speed, "benchmark", teacher_rows)
    overrides = [f"checkpoint={tiny_checkpoint('difareli_pp')}", f"store={synth_store}", "steps=[2]",
                 "names=[ddim]", "reference=null", "limit=1", "progress=false", "runtime.device=cpu"]
    with pytest.raises(FileNotFoundError, match="student=.*no_such.ckpt.*shipped checkpoint"):
        bench_samplers(compose_train(tmp_path / "a", [*overrides, "student=/tmp/no_such.ckpt"],
                                     config_name="bench_samplers"))
    # The shipped student by name: loaded and its cases prepared, then the teacher's rows start.
    with pytest.raises(TeacherRowsStarted):
        bench_samplers(compose_train(tmp_path / "b", [*overrides, "student=difareli_pp_ss-synth64"],
                                     config_name="bench_samplers"))


def test_one_pass_relight_runs_through_the_runtime_denoiser(student_ckpt, synth_store):
    """relight_core hands the runtime to the student: fp32 equals the plain pass bit for bit, bf16 equals autocast
    on the original network bit for bit (the inference copy's contract, contiguous), and channels-last bf16
    stays within bf16 rounding of it."""
    from difareli.lighting import sh
    from difareli.relight.core import relight
    from difareli.runtime.core import Runtime

    rel = Relighter(student_ckpt, device="cpu")
    store = EncodingStore.open(synth_store)
    arrays = rel.source(store, store.ids(split="test")[0]).arrays
    model, names = rel.model, rel.model_inputs
    x0 = image_to_tensor(arrays["image"])[None]
    src = condition_tensors(model, [arrays], "cpu")
    tgt = condition_tensors(model, [retarget(arrays, names, sh.yaw(np.asarray(arrays["light"]), a)) for a in (40, -40)],
                            "cpu")
    src2 = tuple(None if v is None else v.expand(2, *v.shape[1:]) for v in src)
    with torch.no_grad():
        plain = model.relight_once(x0.expand(2, -1, -1, -1), model.condition(*src2), model.condition(*tgt))
        with torch.autocast("cpu", dtype=torch.bfloat16, cache_enabled=False):
            cast = model.relight_once(x0.expand(2, -1, -1, -1), model.condition(*src2), model.condition(*tgt))
    fp32 = relight(model, x0, src, tgt, runtime=Runtime(device="cpu", precision="fp32"))
    assert torch.equal(fp32, plain.float())
    bf16 = relight(model, x0, src, tgt, runtime=Runtime(device="cpu", precision="bf16", memory_format="contiguous"))
    assert torch.equal(bf16, cast.float())
    cl = relight(model, x0, src, tgt, runtime=Runtime(device="cpu", precision="bf16", memory_format="channels_last"))
    assert 0 < (cl - fp32).abs().max() < 0.1 and (cl - cast.float()).abs().mean() < 1e-2


def test_teacher_pairs_march_toward_the_light_records_found_sun(synth_store, tiny_checkpoint, tmp_path):
    """Each pair's target map is marched toward the key sun found from the cast shadows of the record whose light
    it is (its meta keeps the direction), as the benchmark's; ``target_sun=peak``: toward the radiance peak."""
    from difareli.render.retarget import retarget
    from difareli.render import sun_fit

    store = EncodingStore.open(synth_store)
    relighter = Relighter(tiny_checkpoint("difareli_pp"), SAMPLER, device="cpu")
    generate_teacher_pairs(relighter, store, tmp_path / "sun", limit=3, batch_size=3, progress=False)
    generate_teacher_pairs(relighter, store, tmp_path / "peak", limit=3, batch_size=3, progress=False,
                           target_sun="peak")
    sun, peak = _pairs(tmp_path / "sun"), _pairs(tmp_path / "peak")
    moved = 0
    for p, (meta, arrays) in sun.items():
        light = np.asarray(store.read(meta["light_from"], ["light"])["light"])
        found = sun_fit.record_sun(store, meta["light_from"], light)
        np.testing.assert_allclose(meta["sun"], found.direction, atol=1e-12)
        src = relighter.source(store, meta["source"]).arrays
        c = float(meta["shadow"])
        want = retarget(src, ["shadow_map"], light, c, sun=found.direction)["shadow_map"]
        np.testing.assert_allclose(arrays["shadow_map"], want, atol=1e-6)
        np.testing.assert_allclose(peak[p][1]["shadow_map"], retarget(src, ["shadow_map"], light, c)["shadow_map"],
                                   atol=1e-6)
        assert "sun" not in peak[p][0]
        moved += found.moved_deg > 1
    assert moved >= 1  # the found sun is not the peak for at least one light record here
    with pytest.raises(UserError, match="target_sun='east'"):
        generate_teacher_pairs(relighter, store, tmp_path / "bad", limit=1, progress=False, target_sun="east")
