"""Difference-method shadow maps (difareli.jobs.shadow_maps) on a crafted model whose relights are known exactly, and
derived encoding versions (difareli.data.derived): atomic, resumable, provenance, reader selection."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from difareli.data import derived
from difareli.data import encodings
from difareli.jobs import shadow_maps as sm
from difareli.errors import UserError
from difareli.data.store import EncodingStore
from difareli.relight.targets import Targets

ROWS, COLS = slice(12, 20), slice(12, 20)  # an 8x8 square in the middle of a 32 px face
#: The issue-12 rule these tests were written for (Otsu, 3x3 median, no parts zeroed); the recipe has its own tests.
OTSU = {"threshold": "otsu", "median": 3, "zero_parts": ()}


class Crafted(torch.nn.Module):
    """A one-pass 'relighter' whose output is known: 0.5 everywhere, minus 0.4 sigmoid(c) on the square."""

    spatial_inputs: list = []
    nonspatial_inputs = ["shadow"]

    def __init__(self, size: int = 32):
        super().__init__()
        p = torch.zeros(1, 1, size, size)
        p[..., ROWS, COLS] = 1.0
        self.register_buffer("pattern", p)

    def condition(self, spatial, nonspatial):
        return nonspatial  # the raw c, [B, 1]

    def relight_once(self, x0, source, target):
        a = 0.4 * torch.sigmoid(target)[:, :, None, None]
        return (0.5 - a * self.pattern).expand(-1, 3, -1, -1)


@pytest.fixture
def store(synth_store, tmp_path):
    shutil.copytree(synth_store, tmp_path / "store")
    return EncodingStore.open(tmp_path / "store", durable=False)


def test_otsu_threshold_two_modes():
    v = np.r_[np.zeros(900), np.full(100, 0.3)]
    t = sm.otsu_threshold(v)
    assert 0 < t < 0.3
    rng = np.random.default_rng(0)
    v = np.r_[rng.normal(0.0, 0.02, 5000), rng.normal(0.5, 0.02, 1000)]
    assert 0.1 < sm.otsu_threshold(v) < 0.4
    with pytest.raises(ValueError, match="two distinct"):
        sm.otsu_threshold(np.ones(10))


def test_finish_map_threshold_median_and_scale():
    diff = np.zeros((16, 16))
    diff[4:10, 4:12] = 0.2
    diff[14, 1] = 0.9  # an isolated speck: the median filter removes it
    c = -2.0
    out = sm.finish_map(diff, 0.1, 3, c)
    want = np.zeros((16, 16), bool)
    want[4:10, 4:12] = True
    for r, k in ((4, 4), (4, 11), (9, 4), (9, 11)):  # a 3x3 median drops a rectangle's corners (4 of 9 in)
        want[r, k] = False
    np.testing.assert_array_equal(out, (want * encodings.normalise_c(c)).astype(np.float32))
    hit = np.zeros((16, 16), bool)
    hit[:, :8] = True
    np.testing.assert_array_equal(sm.finish_map(diff, 0.1, 3, c, hit) > 0, want & hit)
    np.testing.assert_array_equal(sm.finish_map(diff, 0.1, 1, c) > 0, diff > 0.1)  # no filter


def test_difference_pipeline_on_a_crafted_model(store):
    ids = store.ids()
    for r in ids:
        assert (store.read(r, ["depth"])["depth"][ROWS, COLS] != 0).all(), "the square lies on the face"
    c_min, c_max = sm.c_range(store)
    cs = {r: float(store.read(r, ["shadow"])["shadow"][0]) for r in ids}
    train = [cs[r] for r in store.ids(split="train")]
    assert sm.c_range(store, quantile=0) == (min(train), max(train))  # the paper's strict extremes
    assert (c_min, c_max) == tuple(np.quantile(train, [0.01, 0.99]))  # the default: robust to outliers
    assert min(train) <= c_min < c_max <= max(train)
    with pytest.raises(UserError, match="c_quantile"):
        sm.c_range(store, quantile=0.5)
    rep = sm.compute(Crafted(), store, None, provenance={"checkpoint": "crafted"}, **OTSU, batch_size=3, progress=False)
    assert rep.relit == len(ids) and rep.written == len(ids) and rep.name.startswith("shadow_map@diff-")
    sig = lambda c: 1 / (1 + np.exp(-c))  # noqa: E731
    delta = 0.4 * (sig(c_max) - sig(c_min)) / 2  # luminance difference on the square, [0, 1] units
    square = np.zeros((32, 32), bool)
    square[ROWS, COLS] = True
    filtered = square.copy()
    for r, k in ((12, 12), (12, 19), (19, 12), (19, 19)):
        filtered[r, k] = False
    for r in ids:
        raw = store.read(r, [rep.raw])[rep.raw]
        np.testing.assert_allclose(raw, square * delta, atol=2e-6)
        np.testing.assert_array_equal(store.read(r, [rep.name])[rep.name],
                                      (filtered * encodings.normalise_c(cs[r])).astype(np.float32))
    assert 0 < rep.threshold < delta
    prov = EncodingStore.open(store.root).derived[rep.name]
    assert prov["checkpoint"] == "crafted" and prov["threshold"] == rep.threshold and prov["median"] == 3
    assert prov["threshold_rule"].startswith("otsu") and prov["c_max"] == c_max

    # Reader selection: the chosen version reads under the base name; the plain store keeps the original.
    rid = ids[0]
    chosen = EncodingStore.open(store.root).use_versions({"shadow_map": rep.name.split("@")[1]})
    np.testing.assert_array_equal(chosen.read(rid, ["shadow_map"])["shadow_map"], store.read(rid, [rep.name])[rep.name])
    assert not np.array_equal(EncodingStore.open(store.root).read(rid, ["shadow_map"])["shadow_map"],
                              chosen.read(rid, ["shadow_map"])["shadow_map"]) or not cs[rid] > -6
    with pytest.raises(UserError, match="no shadow_map@nope"):
        EncodingStore.open(store.root).use_versions({"shadow_map": "nope"})

    # Resumable: a rerun relights nothing; a record that lost its raw difference is the only one redone.
    again = sm.compute(Crafted(), store, None, provenance={"checkpoint": "crafted"}, **OTSU, progress=False)
    assert again.relit == 0 and again.name == rep.name and again.threshold == rep.threshold
    derived.path_of(store, ids[1], rep.raw).unlink()
    assert sm.compute(Crafted(), store, None, provenance={"checkpoint": "crafted"}, **OTSU, progress=False).relit == 1
    assert not list(store.records_dir.glob("*/.*tmp*"))  # no scratch files left behind


def test_datamodule_reads_the_chosen_version(store):
    from difareli.lit.datamodule import EncodingsDataModule

    name = derived.declare(store, "shadow_map", "test-1", {"how": "ones"})
    for r in store.ids():
        derived.write(store, r, name, np.ones((32, 32), np.float32))
    dm = EncodingsDataModule(str(store.root), spatial=["shadow_map"], versions={"shadow_map": "test-1"})
    np.testing.assert_array_equal(dm._open().read(store.ids()[0], ["shadow_map"])["shadow_map"], 1.0)


def test_derived_versions_are_checked(store):
    name = derived.declare(store, "shadow_map", "v1", {"a": 1})
    assert derived.declare(store, "shadow_map", "v1", {"a": 1}) == name  # same provenance: a resume
    with pytest.raises(ValueError, match="other provenance"):
        derived.declare(store, "shadow_map", "v1", {"a": 2})
    with pytest.raises(ValueError, match="invalid"):
        derived.version_name("shadow_map", "../x")
    rid = store.ids()[0]
    with pytest.raises(ValueError, match="shape"):
        derived.write(store, rid, name, np.zeros((8, 8), np.float32))
    with pytest.raises(ValueError, match="not a declared"):
        derived.write(store, rid, "shadow_map@v2", np.zeros((32, 32), np.float32))
    assert derived.write(store, rid, name, np.zeros((32, 32), np.float32))
    assert not derived.write(store, rid, name, np.ones((32, 32), np.float32))  # exists: kept
    np.testing.assert_array_equal(store.read(rid, [name])[name], 0.0)
    assert derived.missing(store, name, store.ids()) == store.ids()[1:]
    # A version may cover some records (one split): verify checks the files that are there, whole and shaped.
    assert EncodingStore.open(store.root).verify() == []
    np.save(store.root / "records" / rid / f"{name}.npy", np.zeros((8, 8), np.float32))
    problems = EncodingStore.open(store.root).verify()
    assert problems == [f"{rid}: derived {name} has shape (8, 8), schema wants (32, 32)"]


def test_cli_on_a_trained_difareli_batches_like_one_at_a_time(tiny_checkpoint, store, tmp_path, one_thread):
    # The diffusion path: records inverted together and both c decoded together give the same differences as
    # the relighting core one record at a time (Relighter, uint8 output: within a quantisation step).
    from difareli.cli.shadow_maps import run
    from difareli.relight.relighter import Relighter

    from tests.helpers import compose_train

    ckpt = tiny_checkpoint("difareli")
    ids = store.ids()[:3]
    cfg = compose_train(tmp_path / "run", [f"checkpoint={ckpt}", f"store={store.root}", f"records=[{','.join(ids)}]",
                                           "sampler.steps=3", "batch_size=2", "progress=false", "runtime.device=cpu",
                                           "threshold=0.01", "min_contrast=0"],  # a 20-step toy barely responds to c
                        config_name="shadow_maps")
    rep = run(cfg)
    assert rep.relit == 3 and rep.written == 3 and (tmp_path / "run" / "shadow_maps.json").is_file()
    c_min, c_max = sm.c_range(store)
    r = Relighter(ckpt, cfg.sampler, device="cpu")
    own = np.asarray(store.read(ids[2], ["light"])["light"])
    relit = r.relight(r.source(store, ids[2]), Targets.of([own, own], [c_max, c_min])).astype(np.float64) / 255.0
    y = relit @ np.array([0.2126, 0.7152, 0.0722])
    raw = np.asarray(EncodingStore.open(store.root).read(ids[2], [rep.raw])[rep.raw])
    np.testing.assert_allclose(raw, y[1] - y[0], atol=2.5 / 255)


def test_binary_scores_known_shapes():
    from difareli.evaluation.metrics import binary_scores

    pred = np.zeros((3, 6, 6), bool)
    gt = np.zeros((3, 6, 6), bool)
    pred[0, :2, :3] = True  # 6 px
    gt[0, :2, :] = True     # 12 px, 6 shared
    gt[1, 0, 0] = True      # nothing predicted
    s = binary_scores(pred, gt)
    np.testing.assert_allclose(s["iou"][:2], [0.5, 0.0])
    np.testing.assert_allclose(s["precision"][0], 1.0)
    np.testing.assert_allclose(s["recall"][:2], [0.5, 0.0])
    assert np.isnan(s["precision"][1]) and np.isnan(s["iou"][2]) and np.isnan(s["recall"][2])


def test_quality_script_scores_known_maps(store, tmp_path):
    """scripts/shadow_map_quality.py: labelled versions, only records holding them, IoU against the GT map."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "scripts" / "shadow_map_quality.py"
    spec = importlib.util.spec_from_file_location("shadow_map_quality", path)
    q = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(q)
    gt_name = q.gt_name(store)
    assert gt_name == "shadow_visible_gt"  # the visibly-shadowed mask, in every store this generator writes
    ids = store.ids()[:3]
    # A "perfect" version (the GT support itself) and an empty one, written as derived versions.
    for version, fn in (("perfect", lambda g: (g > 0).astype(np.float32)), ("empty", np.zeros_like)):
        name = derived.declare(store, "shadow_map", version, {"made": version})
        for r in ids:
            derived.write(store, r, name, fn(np.asarray(store.read(r, [gt_name])[gt_name], np.float32)))
    gt_any = [bool((np.asarray(store.read(r, [gt_name])[gt_name]) > 0).any()) for r in ids]
    assert any(gt_any), "the fixture needs a record with a cast shadow"
    q.main(["--store", str(store.root), "--version", "a=perfect", "--version", "empty", "--out", str(tmp_path)])
    text = (tmp_path / "shadow_map_quality.md").read_text()
    assert "(3 records of all splits" in text
    rows = {line.split("|")[1].strip(): line.split("|")[2:-1] for line in text.splitlines() if line.startswith("| ")}
    assert [float(v) for v in rows["difference (a)"][:4]] == [1.0, 1.0, 1.0, 1.0]
    assert float(rows["difference"][0]) == 0.0 and float(rows["difference"][3]) == 0.0
    assert int(rows["difference (a)"][4]) == sum(gt_any)
    csv_rows = (tmp_path / "shadow_map_quality.csv").read_text().splitlines()
    # 3 records x (2 versions, ray-marched toward the fitted and the exact light and toward each one's sun found from
    # the image's cast shadows, on the exact depth toward the exact key sun and toward every exact sun, mesh, key-sun
    # bound, whole face)
    assert len(csv_rows) == 1 + 3 * 11
    assert "ray-marched, its sun found from the image's cast shadows" in rows
    assert [float(v) for v in rows["key sun, exact mesh (upper bound)"][:2]][1] == 1.0  # inside the GT by definition
    whole = [float(v) for v in rows["whole face (baseline)"][:3]]
    assert whole[2] == 1.0 and 0 < whole[0] < 1  # covering the face: recall 1, IoU = the GT's share of the face
    assert (tmp_path / "shadow_map_quality.png").is_file()
    with pytest.raises(SystemExit):
        q.main(["--store", str(store.root), "--version", "nope", "--out", str(tmp_path)])


def test_record_subsets_get_their_own_version_and_a_flat_model_is_refused(store):
    """The global threshold is taken over the chosen records, so another record set is another version; a model
    whose relights do not darken with c gives no positive Otsu threshold and is refused, not written."""
    ids = store.ids()
    a = sm.compute(Crafted(), store, None, provenance={"checkpoint": "crafted"}, **OTSU, ids=ids[:4], progress=False)
    b = sm.compute(Crafted(), store, None, provenance={"checkpoint": "crafted"}, **OTSU, ids=ids[2:6], progress=False)
    full = sm.compute(Crafted(), store, None, provenance={"checkpoint": "crafted"}, **OTSU, progress=False)
    assert len({a.name, b.name, full.name}) == 3 and a.raw == b.raw == full.raw  # raw differences are shared
    assert b.relit == 2 and full.relit == len(ids) - 6  # only records without a raw difference are relit
    prov = EncodingStore.open(store.root).derived
    assert prov[full.name]["records"] == "all" and prov[a.name]["n_records"] == 4

    class Brightens(Crafted):
        def relight_once(self, x0, source, target):
            return 1.0 - super().relight_once(x0, source, target)  # lighter as c grows: differences <= 0

    with pytest.raises(UserError, match="does not darken"):
        sm.compute(Brightens(), store, None, provenance={"checkpoint": "bright"}, **OTSU, progress=False)
    assert not any(k.startswith("shadow_map@diff-") and v.get("checkpoint") == "bright"
                   for k, v in EncodingStore.open(store.root).derived.items())


@pytest.mark.parametrize("config_name,key", [("benchmark", "versions"), ("video", "versions"),
                                             ("relight", "versions"), ("train", "data.versions")])
def test_versions_override_composes_as_documented(config_name, key, tmp_path):
    """``versions.shadow_map=<version>`` (the README's spelling) composes in every reader's config; the default
    null reads the store's own map."""
    from omegaconf import OmegaConf

    from tests.helpers import compose_train

    base = compose_train(tmp_path / "a", [], config_name=config_name)
    assert OmegaConf.select(base, f"{key}.shadow_map", default="missing") is None
    cfg = compose_train(tmp_path / "b", [f"{key}.shadow_map=diff-1a2b"], config_name=config_name)
    assert OmegaConf.select(cfg, f"{key}.shadow_map") == "diff-1a2b"


# ------------------------------------------------------------------------------------------ the authors' recipe
def test_recipe_median_scales_with_the_resolution():
    assert [sm.median_size("auto", r) for r in (32, 64, 128, 256, 512)] == [1, 1, 3, 5, 9]
    assert sm.median_size(7, 64) == 7


def test_otsu_refuses_a_one_peaked_histogram_and_names_what_it_found():
    rng = np.random.default_rng(0)
    gauss = rng.normal(0.0, 0.01, 20000)  # a DiFaReli whose response to c is noise
    t = sm.otsu_threshold(gauss)
    assert abs(t) < 0.005 and 0.4 < (gauss > t).mean() < 0.6  # Otsu cuts near the mean: half the face
    with pytest.raises(UserError, match="one mode, not two.*lower peak"):
        sm.check_two_modes(gauss, t)
    two = np.r_[rng.normal(0.0, 0.005, 9000), rng.normal(0.2, 0.01, 1000)]
    sm.check_two_modes(two, sm.otsu_threshold(two))  # separated modes pass


def test_fixed_threshold_map_on_a_crafted_difference():
    """0.05 on the grey-level difference, parts zeroed, times the face mask and c normalised by a given range."""
    diff = np.zeros((8, 8))
    diff[2:6, 2:6] = 0.06   # above the recipe's threshold
    diff[0, :] = 0.049      # just below: not shadow
    keep = np.ones((8, 8), bool)
    keep[2, 2:6] = False    # an eye row, zeroed
    keep[:, 7] = False      # off the face mask
    out = sm.finish_map(diff, sm.RECIPE_THRESHOLD, 1, -2.0, None, keep, (-4.0, -1.0))
    want = np.zeros((8, 8), bool)
    want[3:6, 2:6] = True
    np.testing.assert_allclose(out, want * (2.0 / 3.0), atol=1e-7)  # (-2 - -4) / (-1 - -4)


def test_defaults_and_a_weak_difareli_is_refused_with_its_contrast(store):
    class Weak(Crafted):
        def relight_once(self, x0, source, target):
            return 0.5 + 0.01 * (super().relight_once(x0, source, target) - 0.5)  # 1% of the response

    with pytest.raises(UserError, match=r"too little spatial contrast.*darker than the rest.*min_contrast=0\.01"):
        sm.compute(Weak(), store, None, provenance={"checkpoint": "weak"}, progress=False)
    rep = sm.compute(Weak(), store, None, provenance={"checkpoint": "weak"}, min_contrast=0, progress=False)
    prov = EncodingStore.open(store.root).derived[rep.name]
    assert (prov["threshold"] == pytest.approx(sm.RELATIVE * prov["response_p99"], rel=0.02)
            and prov["centre"] == "median")
    assert prov["median"] == 1 and prov["zero_parts"] == list(sm.ZERO_PARTS)
    assert prov["contrast"] < 0.01 and prov["c_norm_range"] == "fixed"  # a pre-v3 store: the fixed range
    recipe = sm.compute(Weak(), store, None, provenance={"checkpoint": "weak"}, centre="none", threshold=0.05,
                        min_contrast=0, progress=False)  # the authors' recipe: nothing clears 0.05, an empty map
    assert EncodingStore.open(store.root).derived[recipe.name]["threshold"] == 0.05
    for r in store.ids():
        assert not (store.read(r, [recipe.name])[recipe.name] > 0).any()


class Brightening(Crafted):
    """What a DiFaReli trained on SynthFaces does: raising c darkens the shadow (the square) and brightens the
    rest of the face a little (+0.062 inside shadows, -0.021 elsewhere on the shipped one)."""

    def relight_once(self, x0, source, target):
        out = super().relight_once(x0, source, target)
        return out + 0.3 * torch.sigmoid(target)[:, :, None, None] * (1 - self.pattern)


def test_a_real_response_with_a_global_brightening_is_kept_and_mapped(store):
    """The sign-balance rule refused this response as noise (the lit skin brightens past the cut as often as the
    shadow darkens); centring by the face median and judging by spatial contrast keep it, and the map is the
    square the model darkens."""
    rep = sm.compute(Brightening(), store, None, provenance={"checkpoint": "bright"}, median=3, zero_parts=(),
                     progress=False)
    prov = EncodingStore.open(store.root).derived[rep.name]
    c_min, c_max = rep.c_min, rep.c_max
    sig = lambda c: 1 / (1 + np.exp(-c))  # noqa: E731
    # The square darkens by 0.4 ds / 2 relative to the rest, which brightens by 0.3 ds / 2 (luminance in [0, 1]).
    ds = sig(c_max) - sig(c_min)
    assert prov["contrast"] == pytest.approx((0.4 + 0.3) * ds / 2, rel=1e-3)
    assert prov["coherence"] > 0.5
    square = np.zeros((32, 32), bool)
    square[ROWS, COLS] = True
    for r in store.ids():
        m = store.read(r, [rep.name])[rep.name] > 0
        assert (m & ~square).sum() == 0 and (m & square).sum() >= 0.8 * square.sum()


def test_centring_removes_a_global_shift_and_the_judge_measures_contrast_and_coherence():
    from difareli.jobs import shadow_response as sr

    face = np.zeros((20, 20), bool)
    face[2:18, 2:18] = True
    blob = np.zeros_like(face)
    blob[5:10, 5:10] = True
    d = 0.03 + 0.08 * blob  # a global shift plus a blob 0.08 darker
    c = sr.centred(d, face, "median")
    np.testing.assert_allclose(c[face & ~blob], 0.0, atol=1e-12)
    resp = sr.measure([c], [face], "relative", 0.5)
    assert resp.threshold == pytest.approx(0.04) and resp.contrast == pytest.approx(0.08)
    share = 25 / 256
    assert resp.candidates == pytest.approx(share)  # a 5x5 blob: 9 inner, 12 edge and 4 corner pixels
    assert resp.coherence == pytest.approx(((9 * 8 + 12 * 5 + 4 * 3) / 200 - share) / (1 - share))
    line = np.zeros_like(face)
    line[12, 3:15] = True  # a thin shadow under a brim: 12 pixels, each end with one neighbour
    share = 12 / 256
    got = sr.measure([0.08 * line.astype(float)], [face], 0.04).coherence
    assert got == pytest.approx(((10 * 2 + 2 * 1) / 96 - share) / (1 - share)) and got > sr.MIN_COHERENCE
    rng = np.random.default_rng(0)
    dense = rng.random(face.shape) < 0.4  # speckle at 40% density: as many neighbours as chance gives
    assert sr.measure([0.08 * dense.astype(float)], [face], 0.04).coherence < sr.MIN_COHERENCE  # chance, no more
    speckle = np.zeros_like(face)
    speckle[3:17:3, 3:17:3] = True  # isolated pixels: none has a neighbour
    sp = sr.measure([0.08 * speckle.astype(float)], [face], 0.04)
    assert sp.coherence < 0 and sp.contrast == pytest.approx(0.08)
    with pytest.raises(UserError, match=r"speckle.*coherence -0\.\d+ \(0: speckle\)"):
        sr.judge(sp, None, None, step=7)
    sr.judge(resp, None, None, step=7)  # passes
    with pytest.raises(UserError, match="centre='middle'"):
        sr.check_centre("middle")


def test_records_split_selects_a_split_and_names_an_empty_one(store):
    from omegaconf import OmegaConf

    from difareli.cli.shadow_maps import record_ids

    cfg = OmegaConf.create({"records": None, "records_split": "train"})
    assert record_ids(cfg, store) == store.ids(split="train")
    assert record_ids(OmegaConf.create({"records": ["a"], "records_split": "train"}), store) == ["a"]
    assert record_ids(OmegaConf.create({"records": None, "records_split": None}), store) is None
    with pytest.raises(UserError, match="records_split=nope"):
        record_ids(OmegaConf.create({"records": None, "records_split": "nope"}), store)


def test_a_difareli_whose_response_to_c_is_noise_is_refused(store):
    class Noisy(Crafted):
        def relight_once(self, x0, source, target):
            g = torch.Generator().manual_seed(int(abs(float(target.flatten()[0])) * 1000))  # differs with c
            noise = 0.2 * (torch.rand(x0.shape[0], 1, *x0.shape[-2:], generator=g) - 0.5)
            return (0.5 + noise).expand(-1, 3, -1, -1)

    with pytest.raises(UserError, match=r"speckle, not a shadow.*coherence.*min_coherence=0\.1"):
        sm.compute(Noisy(), store, None, provenance={"checkpoint": "noisy"}, progress=False)
    rep = sm.compute(Noisy(), store, None, provenance={"checkpoint": "noisy"}, min_contrast=0, progress=False)
    prov = EncodingStore.open(store.root).derived[rep.name]
    assert prov["coherence"] < 0.1 and prov["contrast"] > 0


class _Noisy(Crafted):
    """Its two decodes differ by noise, not a shadow; counts the records it relights."""

    calls = 0

    def relight_once(self, x0, source, target):
        type(self).calls += x0.shape[0]
        g = torch.Generator().manual_seed(int(abs(float(target.flatten()[0])) * 1000))
        noise = 0.2 * (torch.rand(x0.shape[0], 1, *x0.shape[-2:], generator=g) - 0.5)
        return (0.5 + noise).expand(-1, 3, -1, -1)


def test_a_refused_difareli_is_refused_before_the_rest_of_the_store(store):
    """check_after: the response is checked once that many records are relit, so the refusal comes before the rest;
    what was relit stays in the raw version and a rerun resumes it (relights nothing twice)."""
    n = len(store.ids())
    assert n > 4
    _Noisy.calls = 0
    with pytest.raises(UserError, match=rf"speckle, not a shadow.*measured on the first 4 of {n} records"):
        sm.compute(_Noisy(), store, None, provenance={"checkpoint": "noisy"}, batch_size=2, check_after=4,
                   progress=False)
    assert _Noisy.calls == 2 * 4  # two decodes (c_min, c_max) of 4 records, not of the whole store
    raw = next(v for v in EncodingStore.open(store.root).derived if "diffraw" in v)
    assert len(derived.missing(store, raw, store.ids())) == n - 4
    _Noisy.calls = 0
    rep = sm.compute(_Noisy(), store, None, provenance={"checkpoint": "noisy"}, batch_size=2, check_after=4,
                     min_contrast=0, progress=False)
    assert _Noisy.calls == 2 * (n - 4) and rep.relit == n - 4 and rep.written == n
