"""DiFaReli preprocessing layout -> EncodingStore, on small fake files written in that layout."""

import numpy as np
import pytest
from PIL import Image

from difareli.data import encodings as E
from difareli.official.importers import BISENET_CLASSES, bisenet_to_parts, import_difareli, read_anno
from difareli.data.store import EncodingStore

H = W = 8
LENS = {"shape": 5, "exp": 3, "pose": 2, "light": 27, "cam": 3, "faceemb": 6, "shadow": 1}
NAMES = ["60922.png", "63252.png", "66646.png"]


def write_anno(path, rows):
    path.write_text("".join(f"{name} " + " ".join(repr(float(x)) for x in vec) + "\n" for name, vec in rows.items()))


def make_layout(root, rng, set_name="valid", shading_folder="deca_masked_face_images_woclip", chw=("63252",)):
    """Write the files DiFaReli's create_dataset.py would, with random values; return them for checking."""
    truth = {k: {n: rng.normal(size=L) for n in NAMES} for k, L in LENS.items()}
    pdir = root / "params" / set_name
    pdir.mkdir(parents=True)
    for k, rows in truth.items():
        write_anno(pdir / f"ffhq-{set_name}-{k}-anno.txt", rows)
    write_anno(pdir / f"ffhq-{set_name}-tform-anno.txt", {n: np.eye(3).ravel() for n in NAMES})  # ignored
    seg = root / "face_segment" / set_name / "anno"
    shade = root / "rendered_images" / shading_folder / set_name
    imgs = root / "images" / set_name
    for d in (seg, shade, imgs):
        d.mkdir(parents=True)
    for n in NAMES:
        stem = n[:-4]
        labels = rng.integers(0, 19, (H, W), dtype=np.uint8)
        labels[0, :] = np.arange(W) + 11  # make sure the remapped classes 11..18 all occur
        Image.fromarray(labels).save(seg / f"anno_{stem}.png")
        sh = rng.normal(size=(H, W, 3)).astype(np.float32) * 2  # unclipped: negative and > 1 values
        np.save(shade / f"{stem}.npy", sh.transpose(2, 0, 1) if stem in chw else sh)
        img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        Image.fromarray(img).save(imgs / n)
        truth.setdefault("labels", {})[n] = labels
        truth.setdefault("shading", {})[n] = sh
        truth.setdefault("image", {})[n] = img
    return truth


def test_bisenet_mapping_table():
    expected = {"background": "background", "skin": "skin", "l_brow": "l_brow", "r_brow": "r_brow",
                "l_eye": "l_eye", "r_eye": "r_eye", "eye_g": "skin", "l_ear": "skin", "r_ear": "skin",
                "ear_r": "skin", "nose": "nose", "mouth": "mouth", "u_lip": "u_lip", "l_lip": "l_lip",
                "neck": "neck", "neck_l": "neck", "cloth": "clothes", "hair": "hair", "hat": "hat"}
    got = bisenet_to_parts(np.arange(19, dtype=np.uint8))
    assert [E.MASK_PARTS[i] for i in got] == [expected[c] for c in BISENET_CLASSES]
    with pytest.raises(ValueError, match="label 19"):
        bisenet_to_parts(np.array([[19]], np.uint8))


def test_read_anno_checks_lengths(tmp_path):
    p = tmp_path / "x-anno.txt"
    p.write_text("a.png 1 2 3\nb.png 4 5\n")
    with pytest.raises(ValueError, match=r"x-anno.txt:2: 2 values, expected 3"):
        read_anno(p)
    p.write_text("a.png 1 2.5e-1\n\nb.png -4 5\n")
    got = read_anno(p)
    np.testing.assert_array_equal(got["a.png"], [1, 0.25])
    np.testing.assert_array_equal(got["b.png"], [-4, 5])


def test_import_roundtrip(tmp_path, rng):
    src = tmp_path / "src"
    truth = make_layout(src, rng)
    rep = import_difareli(src, "valid", tmp_path / "store", images_dir=src / "images" / "valid", durable=False)
    assert rep.written == ["60922", "63252", "66646"] and not rep.skipped_existing
    st = EncodingStore.open(tmp_path / "store")
    assert st.dims == {"H": H, "W": W, "S": 10, "D": 6}
    assert set(st.encodings) == {"image", "light", "shape", "cam", "identity", "shadow", "shading", "masks",
                                 "face_mask", "background"}
    assert st.store_meta["shape_layout"] == {"shape": [0, 5], "exp": [5, 8], "pose": [8, 10]}
    assert st.verify(check_values=True) == []
    face_idx = [E.PART_INDEX[p] for p in E.FACE_PARTS]
    fg_idx = [E.PART_INDEX[p] for p in E.FOREGROUND_PARTS]
    for n in NAMES:
        rid = n[:-4]
        r = st.read(rid)
        light = truth["light"][n]
        # row-major 9x3: coefficient k, channel c is value 3k + c of the anno line
        assert r["light"][4, 2] == np.float32(light[14]) and r["light"][8, 0] == np.float32(light[24])
        np.testing.assert_allclose(r["shape"], np.concatenate([truth[k][n] for k in ("shape", "exp", "pose")]),
                                   rtol=1e-6)
        np.testing.assert_allclose(r["cam"], truth["cam"][n], rtol=1e-6)
        np.testing.assert_allclose(r["identity"], truth["faceemb"][n], rtol=1e-6)
        np.testing.assert_allclose(r["shadow"], truth["shadow"][n], rtol=1e-6)
        np.testing.assert_array_equal(r["shading"], truth["shading"][n])  # CHW file for 63252 transposed back
        np.testing.assert_array_equal(r["image"], truth["image"][n])
        lab = truth["labels"][n]
        np.testing.assert_array_equal(r["masks"], bisenet_to_parts(lab))
        assert (r["masks"][lab == 6] == E.PART_INDEX["skin"]).all()  # eyeglasses -> skin
        assert (r["masks"][lab == 16] == E.PART_INDEX["clothes"]).all()
        np.testing.assert_array_equal(r["face_mask"], np.isin(r["masks"], face_idx))
        fg = np.isin(r["masks"], fg_idx)
        assert (r["background"][fg] == 0).all()
        np.testing.assert_array_equal(r["background"][~fg], truth["image"][n][~fg])
        assert st.meta(rid) == {"split": "valid", "subject": rid, "source": "difareli", "image_name": n}
    assert st.ids(split="valid") == ["60922", "63252", "66646"]


def test_resume_and_overwrite(tmp_path, rng):
    src = tmp_path / "src"
    make_layout(src, rng)
    out = tmp_path / "store"
    rep = import_difareli(src, "valid", out, limit=2, durable=False)
    assert rep.written == ["60922", "63252"]
    assert "image" not in rep.store.encodings and "background" not in rep.store.encodings  # no images_dir
    rep = import_difareli(src, "valid", out, durable=False)
    assert rep.written == ["66646"] and rep.skipped_existing == ["60922", "63252"]
    rep = import_difareli(src, "valid", out, overwrite=True, durable=False)
    assert rep.written == ["60922", "63252", "66646"]
    with pytest.raises(ValueError, match="differing dims"):
        import_difareli(src, "valid", out, size=4, durable=False)


def test_missing_inputs_name_file_and_producer(tmp_path, rng):
    src = tmp_path / "src"
    make_layout(src, rng)
    (src / "params" / "valid" / "ffhq-valid-faceemb-anno.txt").unlink()
    with pytest.raises(FileNotFoundError, match=r"ffhq-valid-faceemb-anno.txt.*ArcFace"):
        import_difareli(src, "valid", tmp_path / "a")
    # without the identity encoding the import goes through
    rep = import_difareli(src, "valid", tmp_path / "b", encodings=["light", "shape", "cam"], durable=False)
    assert len(rep.written) == 3 and rep.store.dims == {"S": 10}
    (src / "rendered_images").rename(src / "renders_elsewhere")
    with pytest.raises(FileNotFoundError, match=r"deca_masked_face_images_woclip/valid.*DECA"):
        import_difareli(src, "valid", tmp_path / "c", encodings=["shading"])
    rep = import_difareli(src, "valid", tmp_path / "c", encodings=["shading"], durable=False,
                          shading_dir=src / "renders_elsewhere" / "deca_masked_face_images_woclip" / "valid")
    assert rep.store.dims == {"H": H, "W": W} and len(rep.written) == 3
    (src / "face_segment" / "valid" / "anno" / "anno_63252.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"'63252.png'.*anno_63252.png missing"):
        import_difareli(src, "valid", tmp_path / "d", encodings=["light", "masks"])
    rep = import_difareli(src, "valid", tmp_path / "e", encodings=["light", "masks"], strict=False, durable=False)
    assert rep.written == ["60922", "66646"] and list(rep.skipped_incomplete) == ["63252.png"]
    with pytest.raises(ValueError, match="need images_dir"):
        import_difareli(src, "valid", tmp_path / "f", encodings=["image"])


def test_readme_folder_name_and_resizing(tmp_path, rng):
    src = tmp_path / "src"
    truth = make_layout(src, rng, shading_folder="deca_masked_face_woclip", chw=())
    big = np.zeros((2 * H, 2 * W, 3), np.uint8)
    Image.fromarray(big).save(src / "images" / "valid" / "60922.png")  # now differs from the label map size
    with pytest.raises(ValueError, match="pass size="):
        import_difareli(src, "valid", tmp_path / "a", images_dir=src / "images" / "valid")
    rep = import_difareli(src, "valid", tmp_path / "b", images_dir=src / "images" / "valid", size=4, durable=False)
    st = rep.store
    assert st.dims["H"] == st.dims["W"] == 4 and st.verify() == []
    r = st.read("63252", ["masks", "shading"])
    # nearest-neighbour labels stay labels of the source; bilinear shading stays within the source range
    assert set(np.unique(r["masks"])) <= set(np.unique(bisenet_to_parts(truth["labels"]["63252.png"])))
    src_sh = truth["shading"]["63252.png"]
    assert src_sh.min() <= r["shading"].min() and r["shading"].max() <= src_sh.max()


def test_chunked_param_files_merge(tmp_path, rng):
    src = tmp_path / "src"
    truth = make_layout(src, rng)
    pdir = src / "params" / "valid"
    light = pdir / "ffhq-valid-light-anno.txt"
    lines = light.read_text().splitlines(keepends=True)
    light.unlink()
    (pdir / "ffhq-0-2-valid-light-anno.txt").write_text("".join(lines[:2]))
    (pdir / "ffhq-2-3-valid-light-anno.txt").write_text("".join(lines[2:]))
    rep = import_difareli(src, "valid", tmp_path / "s", encodings=["light"], durable=False)
    assert rep.written == ["60922", "63252", "66646"]
    np.testing.assert_allclose(rep.store.read("66646", ["light"])["light"].ravel(), truth["light"]["66646.png"],
                               rtol=1e-6)
