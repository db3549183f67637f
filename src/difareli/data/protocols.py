"""Subject splits and the two evaluation protocols of SPEC 11 for SynthFaces.

Subjects come in *light groups* of ``group_size`` consecutive subjects that are rendered under the same
lights (light ``j`` of every member is identical). That is what makes protocol (ii) checkable: the target
light is estimated from another subject ``b`` under light ``j`` and the ground truth is subject ``a`` under
that very light. Splits assign whole groups, so a test subject's partners are test subjects too.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from difareli.errors import UserError
from difareli.utils.fileio import write_text_atomic

SPLITS = ("train", "val", "test")
SPLITS_FILE = "splits.json"
PROTOCOLS_FILE = "protocols.json"
#: The two protocols (SPEC 11), in table order, and the short names metric keys use (``val/dssim/same``):
#: (i) ``same_subject``, the light taken from the same person; (ii) ``different_subject``, from another person.
PROTOCOLS = {"same_subject": "same", "different_subject": "different"}


def record_id(subject: int, light: int) -> str:
    """The store id of subject ``subject`` under light ``light``, e.g. ``s00042_l2``."""
    return f"s{subject:05d}_l{light}"


def subject_name(subject: int) -> str:
    return f"s{subject:05d}"


def light_group(subject: int, group_size: int) -> int:
    """Index of the light group of ``subject``."""
    return subject // group_size


def assign_splits(subjects: int, fractions: dict[str, float], group_size: int, seed: int) -> dict[str, list[int]]:
    """Split subject indices ``0..subjects-1`` into train/val/test by whole light groups.

    Group counts per split are ``round(fraction * groups)`` for val and test (at least one group each when
    the fraction is positive and there are at least three groups); train gets the rest. The group order is
    a permutation drawn from ``seed`` alone, so the same arguments always give the same splits.
    """
    unknown = set(fractions) - set(SPLITS)
    if unknown:
        raise UserError(f"splits: unknown split names {sorted(unknown)}; use {list(SPLITS)}")
    fr = {k: float(fractions.get(k, 0.0)) for k in SPLITS}
    if any(v < 0 for v in fr.values()) or sum(fr.values()) <= 0:
        raise UserError(f"splits: fractions must be >= 0 with a positive sum, got {fr}")
    total = sum(fr.values())
    fr = {k: v / total for k, v in fr.items()}
    n_groups = -(-subjects // group_size)
    counts = {}
    for k in ("test", "val"):
        n = int(round(fr[k] * n_groups))
        if fr[k] > 0 and n == 0 and n_groups >= 3:
            n = 1
        counts[k] = n
    counts["train"] = n_groups - counts["test"] - counts["val"]
    if counts["train"] < 0 or (fr["train"] > 0 and counts["train"] == 0 and n_groups >= 3):
        raise UserError(f"splits: {n_groups} light groups are too few for fractions {fr}")
    order = np.random.default_rng([seed, 0x5B117]).permutation(n_groups)
    out: dict[str, list[int]] = {}
    start = 0
    for k in ("test", "val", "train"):
        groups = order[start:start + counts[k]]
        start += counts[k]
        out[k] = sorted(s for g in groups for s in range(g * group_size, min((g + 1) * group_size, subjects)))
    return {k: out[k] for k in SPLITS}


def split_of(splits: dict[str, list[int]]) -> dict[int, str]:
    """Subject index -> split name."""
    return {s: name for name, subs in splits.items() for s in subs}


def protocol_pairs(test_subjects: list[int], lights: int, group_size: int) -> dict[str, list[dict[str, str]]]:
    """Pair lists of SPEC 11 over the test subjects.

    Each pair names ``source`` (subject a under light i), ``light_source`` (the record the target light is
    estimated from) and ``target`` (ground truth: a under light j), for every i != j:
    - ``same_subject``: light_source = (a, j);
    - ``different_subject``: light_source = (b, j) for each other member b of a's light group.
    """
    members: dict[int, list[int]] = {}
    for s in sorted(test_subjects):
        members.setdefault(light_group(s, group_size), []).append(s)
    same, diff = [], []
    for a in sorted(test_subjects):
        others = [b for b in members[light_group(a, group_size)] if b != a]
        for i in range(lights):
            for j in range(lights):
                if i == j:
                    continue
                src, gt = record_id(a, i), record_id(a, j)
                same.append({"source": src, "light_source": gt, "target": gt})
                diff.extend({"source": src, "light_source": record_id(b, j), "target": gt} for b in others)
    return {"same_subject": same, "different_subject": diff}


def _write_json(path: Path, obj) -> None:
    write_text_atomic(path, json.dumps(obj, indent=1) + "\n")


def write_split_files(root: str | os.PathLike, splits: dict[str, list[int]], lights: int, group_size: int,
                      seed: int) -> tuple[Path, Path]:
    """Write ``splits.json`` (subject names per split) and ``protocols.json`` into the store root."""
    root = Path(root)
    split_doc = {"seed": seed, "light_group_size": group_size,
                 "splits": {k: [subject_name(s) for s in v] for k, v in splits.items()}}
    pairs = protocol_pairs(splits["test"], lights, group_size)
    proto_doc = {"split": "test", "lights": lights,
                 "fields": {"source": "record relit", "light_source": "record the target light is taken from",
                            "target": "ground-truth record"}, **pairs}
    _write_json(root / SPLITS_FILE, split_doc)
    _write_json(root / PROTOCOLS_FILE, proto_doc)
    return root / SPLITS_FILE, root / PROTOCOLS_FILE
