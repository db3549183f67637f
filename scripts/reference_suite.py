"""The reference suite: every shipped model beside identity and the Lambertian ratio image (estimated inputs) on
SynthFaces stores generated with a seed none of them trained on, both protocols, the paper's metric rule, each
model at the defaults a user gets (the default sampler; one pass for a student). Mean ± standard error and s/img,
then the paired differences of every two rows on the same pairs (DSSIM, MSE, LPIPS: mean, bootstrap 95% CI,
Wilcoxon p, and a sentence naming the significant orderings) and the table broken down by the target light's
category and by the target's visible-shadow share (``difareli.evaluation.paired``).

One table per store: SynthFaces v2 (``inputs=estimated_light``: light and shadow estimated, geometry exact, what
the shipped models trained on) and v3 (every input estimated, as a user has them). Writes ``<out>/suite.md`` (and
``<out>/<store>/suite.csv``, ``<out>/<store>/paired.csv``) and, with ``--ship``,
``src/difareli/checkpoints/suite.md`` (package data: ``difareli-demo`` prints it). Runs resume: a model's rows
already in ``<out>`` with the same settings are reused (``scripts/release_reference.py --out <out>`` writes the
same run folders).

    difareli-synth out_dir=data/unseen_v2_s777 subjects=100 lights=4 resolution=64 seed=777 realism=full \\
        inputs=estimated_light workers=2
    difareli-synth out_dir=data/unseen_v3_s777 subjects=100 lights=4 resolution=64 seed=777 workers=2
    python scripts/reference_suite.py --store data/unseen_v2_s777 data/unseen_v3_s777 --pairs 100 --out runs/suite \
        --ship
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections import Counter
from pathlib import Path
from typing import Sequence

from difareli.evaluation import paired, tables
from difareli.checkpoints import zoo
from difareli.diffusion import DEFAULT_SAMPLER, PRESETS
from difareli.utils.fileio import write_text_atomic
from difareli.jobs.compare import compare_to_baselines
from difareli.synth.command import synth_command


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", nargs="+", required=True,
                    help="SynthFaces stores of a seed no shipped model trained on (one table each)")
    ap.add_argument("--store-cmd", nargs="*", default=None,
                    help="the command that made each store (default: read back from each store's header)")
    ap.add_argument("--pairs", type=int, default=100, help="pairs per protocol")
    ap.add_argument("--out", required=True, help="folder of the benchmark runs (resumed), one sub-folder per store")
    ap.add_argument("--models", nargs="*", default=None,
                    help="shipped names or label=<checkpoint path> (default: every shipped name)")
    ap.add_argument("--pool", action="store_true",
                    help="first a table of every store's pairs pooled (record ids prefixed with the store's name), "
                         "then each store's own table: several fresh seeds judged together and one by one")
    ap.add_argument("--paired-metrics", nargs="+", default=list(tables.METRICS),
                    help="the columns the paired comparisons test (default: DSSIM, MSE, LPIPS; e.g. add "
                         "light_angle_gt light_angle)")
    ap.add_argument("--guidance", type=float, default=None,
                    help="the models' light guidance (sampler.guidance; default: the default sampler's)")
    ap.add_argument("--ship", action="store_true", help="also write src/difareli/checkpoints/suite.md")
    ap.add_argument("--note", default="", help="a paragraph after the tables (where and how it was measured)")
    ap.add_argument("--cards", action="store_true",
                    help="also write each shipped card's paired comparisons (its <name>.md and <name>/README.md)")
    a = ap.parse_args()

    start = time.perf_counter()
    out = Path(a.out)
    # Read before the long work, so a store no header describes stops the run at once.
    store_cmd = a.store_cmd if a.store_cmd is not None else [synth_command(store) for store in a.store]
    claims: dict[str, list[str]] = {}
    pooled: list[tables.Record] = []
    labels: dict[str, str] = {}
    sections = [section(store, a.models or zoo.available(), a.pairs, out / Path(store).name, claims,
                        pooled if a.pool else None, a.guidance, labels, a.paired_metrics)
                for store in a.store]
    if a.pool:
        sections.insert(0, pooled_section(a.store, pooled, out, labels, a.paired_metrics))
    extra = ("" if a.paired_metrics == list(tables.METRICS) else f" --paired-metrics {' '.join(a.paired_metrics)}")
    command = (f"python scripts/reference_suite.py{' --pool' if a.pool else ''} --store {' '.join(a.store)} "
               f"--pairs {a.pairs} --out <folder>{' --models ' + ' '.join(a.models) if a.models else ''}{extra}")
    text = "\n".join([*sections, *([a.note, ""] if a.note else []), "Reproduce:", "", "```bash", *store_cmd, command,
                      "```", ""])
    if a.cards:
        for name, lines in claims.items():
            write_card_claims(name, lines, [*store_cmd, command])
    write_text_atomic(out / "suite.md", text)
    if a.ship:
        write_text_atomic(zoo.SHIPPED_DIR / "suite.md", text)
    print(text)
    print(f"{time.perf_counter() - start:.0f} s; {out / 'suite.md'}")


def section(store: str, models: list[str], pairs: int, out: Path, claims: dict[str, list[str]] | None = None,
            pooled: list[tables.Record] | None = None, guidance: float | None = None,
            labels: dict[str, str] | None = None, metrics: Sequence[str] = tables.METRICS) -> str:
    """Every model (and identity, Lambertian, run once) on ``store``; the table and what it measured. ``claims``
    gets, per shipped name, the sentence of its paired comparisons on this store (:func:`model_claims`);
    ``pooled`` gets the store's rows with their record ids prefixed by the store's name; ``labels`` each row's
    label and what it is."""
    sampler = PRESETS[DEFAULT_SAMPLER].to_config()
    if guidance is not None:
        sampler["guidance"] = guidance
    runs, names, rows = {}, {}, {}
    for name in models:
        # Rows named after the shipped name (less its resolution): two shipped checkpoints of one variant differ;
        # a checkpoint path is named by the label before its "=" (label=path), else by its variant.
        label, _, path = name.rpartition("=") if "=" in name else ("", "", name)
        row = label or (name.rsplit("-", 1)[0] if name in zoo.available() else None)
        comparison = compare_to_baselines(store, path, sampler, out, pairs=pairs, progress=True, reuse=True,
                                          model_name=row)
        runs.update(comparison.runs)  # identity and Lambertian are the same runs for every model (resumed)
        names[comparison.facts["model"]] = f"`{name}` ({comparison.facts['sampler']})"
        rows[name] = comparison.facts["model"]
    records = [r for run in runs.values() for r in run.records]
    if labels is not None:
        labels.update(names)
    if pooled is not None:
        pooled += [dataclasses.replace(r, record_id=f"{Path(store).name}/{r.record_id}") for r in records]
    if claims is not None:
        for name, row in rows.items():
            claims.setdefault(name, []).append(model_claims(records, row, store))
    table = tables.summarize(records)
    table.to_csv(out / "suite.csv")
    counts = sorted({n for run in runs.values() for n in Counter(r.protocol for r in run.records).values()})
    return "\n".join([
        f"**{store}**: {' and '.join(map(str, counts))} pairs per protocol (a seed no shipped model trained on), "
        "target lights fitted to the target images and c estimated (no oracle inputs), every model at its defaults."
        + rows_sentence(names), "", table.to_markdown(), "", comparisons(records, table.methods, out / "paired.csv",
                                                                 metrics=metrics)])


def rows_sentence(labels: dict[str, str] | None) -> str:
    """The sentence naming each row's label and what it is (``Rows: `<label>` = <what>; ...``, empty without
    labels): what a reader, and the demo's verdict (``cli.demo.suite_verdict``), look a row up by."""
    return " Rows: " + "; ".join(f"`{row}` = {what}" for row, what in labels.items()) + "." if labels else ""


def pooled_section(stores: list[str], records: list[tables.Record], out: Path,
                   labels: dict[str, str] | None = None, metrics: Sequence[str] = tables.METRICS) -> str:
    """The pairs of every store in one table and one set of paired comparisons (a pair is its store and record);
    ``labels``: each row's label and what it is (the Rows sentence a reader, and the demo's verdict, looks up)."""
    table = tables.summarize(records)
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / "pooled.csv")
    counts = Counter(r.protocol for r in records if r.method == records[0].method) if records else Counter()
    per = ", ".join(f"{n} {p}" for p, n in sorted(counts.items()))
    return "\n".join([
        f"**Pooled: {', '.join(stores)}** ({per} pairs in all; each store a seed no shipped model trained on), "
        "target lights fitted to the target images and c estimated, every model at its defaults."
        + rows_sentence(labels), "",
        table.to_markdown(), "", comparisons(records, table.methods, out / "pooled_paired.csv", metrics=metrics)])


#: The strata the suite breaks its table down by, with their headings.
BREAKDOWNS = {"light_category": "the target light's category",
              "shadow_share": "the share of the face in the target's visible cast shadow"}


def comparisons(records: list[tables.Record], methods: list[str], csv_path: Path | None = None,
                n_boot: int = paired.N_BOOT, seed: int = 0, metrics: Sequence[str] = tables.METRICS) -> str:
    """Paired differences of every two ``methods`` on the pairs both scored (DSSIM, MSE, LPIPS), with the sentence
    naming the significant orderings, then the summary broken down by each of :data:`BREAKDOWNS`."""
    rows, notes = paired.compare(records, metrics, n_boot=n_boot, seed=seed, strict=False, methods=methods)
    if csv_path is not None:
        write_text_atomic(csv_path, paired.to_csv(rows))
    out = ["Paired differences, every two rows on the same pairs:", "", paired.to_markdown(rows, notes, n_boot, seed)]
    for by, what in BREAKDOWNS.items():
        if any(r.status == "ok" and not str(r.info.get(by, "")).strip() for r in records):
            out += [f"No breakdown by {what}: some runs have no {by} column (rerun them with this difareli).", ""]
            continue
        strata = tables.summarize(paired.stratify(records, by), methods, metrics=tables.METRICS)
        bins = f"; bins {list(paired.SHADOW_BINS)}" if by == "shadow_share" else ""
        out += [f"By {what} ({by}{bins}):", "", strata.to_markdown_long()]
    return "\n".join(out)


def model_claims(records: list[tables.Record], row: str, store: str, n_boot: int = paired.N_BOOT) -> str:
    """What a card may claim of its model's row ``row`` on ``store``: its paired comparisons (DSSIM, MSE, LPIPS)
    against every other row of the suite, as the sentence :func:`difareli.evaluation.paired.significance` writes."""
    rows, _ = paired.compare(records, tables.METRICS, n_boot=n_boot, strict=False)
    mine = [c for c in rows if row in (c.a, c.b)]
    n = sorted({c.n for c in mine})
    return (f"On `{store}` ({' or '.join(map(str, n))} pairs per protocol, a seed it never saw; row `{row}`): "
            + paired.significance(mine))


#: The heading of the card section :func:`write_card_claims` owns (replaced on each run, the rest kept).
CLAIMS_HEADING = "## Paired comparisons (reference suite)"


def write_card_claims(name: str, lines: list[str], reproduce: list[str]) -> None:
    """Put ``lines`` under :data:`CLAIMS_HEADING` in the shipped card ``<name>.md`` and its folder's README.md
    (the same text: the folder's card is the shipped card), replacing that section if it is there."""
    body = "\n\n".join([CLAIMS_HEADING, *lines, "Reproduce:\n\n```bash\n" + "\n".join(reproduce) + "\n```"])
    for path in (zoo.SHIPPED_DIR / f"{name}.md", zoo.SHIPPED_DIR / name / "README.md"):
        if not path.is_file():
            continue
        text = path.read_text()
        if CLAIMS_HEADING in text:
            start = text.index(CLAIMS_HEADING)
            nxt = text.find("\n## ", start + len(CLAIMS_HEADING))
            text = text[:start] + body + ("\n" + text[nxt:] if nxt >= 0 else "\n")
        else:  # before "## Intended use" (after the benchmark), else at the end
            at = text.find("\n## Intended use")
            text = (text[:at] + "\n" + body + "\n" + text[at:]) if at >= 0 else text.rstrip("\n") + "\n\n" + body + "\n"
        write_text_atomic(path, text)


if __name__ == "__main__":
    main()
