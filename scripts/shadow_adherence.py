"""How much a DiFaReli++ darkens the inside of the shadow map it is given, against what a real cast shadow removes
(difareli.evaluation.map_response), on the shadowed records of a SynthFaces v3 store.

    python scripts/shadow_adherence.py --checkpoint difareli_pp-synth64 --store data/unseen_v3_s4242 --limit 40
    python scripts/shadow_adherence.py --checkpoint <run>/checkpoints/last.ckpt --store ... --version visible

Prints a Markdown table (map kind | darkening ± SE | real removal | ratio | records) and writes it, with a CSV of
every record, under --out.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

from tqdm.auto import tqdm

from difareli.data.store import EncodingStore
from difareli.diffusion.spec import SamplerSpec
from difareli.evaluation import map_response as mr
from difareli.relight.relighter import Relighter


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--store", required=True)
    ap.add_argument("--version", default=None, help="the shadow_map version the input's own condition reads")
    ap.add_argument("--split", default=None, help="only this split's records (default: every record)")
    ap.add_argument("--limit", type=int, default=40, help="shadowed records measured (the first ones)")
    ap.add_argument("--sampler", default="unipc")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--precision", default="auto")
    ap.add_argument("--out", default="logs/shadow_adherence")
    args = ap.parse_args()
    store = EncodingStore.open(args.store)
    if args.version:
        store = store.use_versions({"shadow_map": args.version})
    ids = mr.shadowed_records(store, store.ids(split=args.split) if args.split else store.ids())[:args.limit]
    r = Relighter(args.checkpoint, SamplerSpec(name=args.sampler, steps=args.steps),
                  runtime={"precision": args.precision})
    rows = [row for rid in tqdm(ids, desc="records") for row in mr.respond(r, store, rid)]
    summary = mr.summarise(rows)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "records.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["record", "map", "darkening", "inside", "real", "map_share"])
        w.writerows([[x.record, x.kind, f"{x.darkening:.5f}", f"{x.inside:.5f}", f"{x.real:.5f}", f"{x.map_share:.4f}"]
                     for x in rows])
    lines = [f"checkpoint {args.checkpoint}; store {args.store} ({len(ids)} shadowed records, visible shadow >= "
             f"{mr.SHADOWED_SHARE:.0%} of the face); {args.sampler}-{args.steps}, precision {r.runtime.precision}",
             "", "| map | darkening inside it less the rest of the face (± SE) | ratio | drop inside it | ratio | "
             "real cast shadow removes | records |", "|---|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {k} | {s['darkening']:.4f} ± {s['darkening_se']:.4f} | {s['ratio']:.2f} | {s['inside']:.4f} | "
              f"{s['inside_ratio']:.2f} | {s['real']:.4f} | {s['records']} |" for k, s in summary.items()]
    text = "\n".join(lines) + "\n"
    (out / "shadow_adherence.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
