"""A benchmark run's result (:class:`BenchmarkResult`: its rows, what it states about its inputs, the fitted lights'
errors) and the files it leaves in its run dir (:func:`write_outputs`), for a run and for a rescore alike."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from difareli.evaluation import tables
from difareli.utils.fileio import atomic_path, write_json_atomic, write_text_atomic

#: The light-estimation errors of a run (where the store holds exact lights).
LIGHT_CSV = "light_estimation.csv"


@dataclass
class BenchmarkResult:
    records: list[tables.Record]
    #: which inputs were estimated and which were oracle (stated in summary.md and provenance.json)
    provenance: dict[str, str] = field(default_factory=dict)
    light_errors: list[dict] = field(default_factory=list)
    paths: dict[str, Path] = field(default_factory=dict)
    #: protocol -> metric -> (mean, SE, n) of the pairs scored in this run, from the torchmetrics Metrics
    metric_stats: dict[str, dict[str, tuple[float, float, int]]] = field(default_factory=dict)
    #: lines under the table: why an extra metric column is absent
    notes: list[str] = field(default_factory=list)

    @property
    def table(self) -> tables.Table:
        table = tables.summarize(self.records)
        table.remarks = list(self.notes)
        return table

    def light_summary(self) -> str:
        """Markdown table of the light-estimation errors (mean ± SE per protocol and light)."""
        if not self.light_errors:
            return ""
        lines = ["| protocol | light | n | rel. irradiance error | after best gain |", "|---|---|---:|---:|---:|"]
        keys = list(dict.fromkeys((e["protocol"], e["light"]) for e in self.light_errors))
        for p, which in keys:
            rows = [e for e in self.light_errors if e["protocol"] == p and e["light"] == which]
            rel = tables.mean_se(r["rel_error"] for r in rows)
            free = tables.mean_se(r["rel_error_gain_free"] for r in rows)
            lines.append(f"| {tables.PROTOCOL_LABELS.get(p, p)} | {which} | {rel.n} | {_pm(rel)} | {_pm(free)} |")
        return "\n".join(lines) + "\n"


def _pm(s: tables.Stat) -> str:
    return f"{s.mean:.4f} ± {s.se:.4f}" if math.isfinite(s.se) else f"{s.mean:.4f}"


def write_outputs(result: BenchmarkResult, out_dir: Path, caption: str | None = None) -> dict[str, Path]:
    """Per-image CSV, summary tables (Markdown with the light-estimation errors, CSV, LaTeX), light CSV; each
    written atomically (a full disk is one line naming the file and leaves the previous one whole)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    table = result.table
    paths = {"per_image": out_dir / tables.PER_IMAGE_CSV}
    with atomic_path(paths["per_image"]) as tmp:
        tables.write_records(tmp, result.records)
    md = table.to_markdown()
    if result.provenance:  # every table says which inputs were estimated and which were oracle (and the mask)
        md = "Inputs: " + "; ".join(f"{k}: {v}" for k, v in result.provenance.items()) + "\n\n" + md
        paths["provenance"] = write_json_atomic(out_dir / "provenance.json", result.provenance)
    if result.light_errors:
        md += "\nLight estimation (relative irradiance error on the ground truth's face normals):\n\n"
        md += result.light_summary()
    paths["summary_md"] = write_text_atomic(out_dir / "summary.md", md)
    paths["summary_csv"] = write_text_atomic(out_dir / "summary.csv", table.to_csv())
    paths["summary_tex"] = write_text_atomic(out_dir / "summary.tex", table.to_latex(caption=caption))
    if result.light_errors:
        cols = ["protocol", "record_id", "light", "from", "rel_error", "rel_error_gain_free"]
        lines = [",".join(cols)] + [",".join(str(e[c]) for c in cols) for e in result.light_errors]
        paths["light_csv"] = write_text_atomic(out_dir / LIGHT_CSV, "\n".join(lines) + "\n")
    return paths
