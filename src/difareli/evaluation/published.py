"""The paper's published Multi-PIE figures (DiFaReli++, TPAMI 2026), quoted as facts for tables beside ours.

Source: ``paper/difareli_pp.tex``. Means of both protocols are Table I ("State-of-the-art comparison on
Multi-PIE", ``tab:TL``); the standard errors are the appendix's full table of Table I's top half
(``tab:full``, "We report the means and standard errors"), so protocol (i) has SEs and protocol (ii) has none
(rendered ``n/a``). SfSNet, DPR and SIPR appear only in that appendix table (protocol (i)). The n are the paper's
test-set sizes: (i) "862 testing samples from 329 subjects" (Hou et al.'s set), (ii) "200 random triplets".
The paper's metrics are DSSIM, MSE and LPIPS on the face region of its own face parser (BiSeNet) under the
authors' evaluator, i.e. this project's ``metrics.rule=paper``.
"""

from __future__ import annotations

import math

from difareli.errors import UserError
from difareli.evaluation.tables import Stat, Table

SOURCE = ("the DiFaReli++ paper (TPAMI 2026) Table I, SEs from its appendix table of Table I's top half; "
          "protocol (ii) has no published SEs")
N = {"same": 862, "different": 200}

#: The figures as printed: (i) DSSIM SE MSE SE LPIPS SE | (ii) DSSIM MSE LPIPS ("-": not in that protocol's table).
_PRINTED = """
SfSNet                           | 0.2918 0.0013 0.0961 0.0017 0.5222 0.0025 | -      -      -
DPR                              | 0.1599 0.0019 0.0852 0.0018 0.2644 0.0028 | -      -      -
SIPR                             | 0.1539 0.0015 0.0166 0.0004 0.2764 0.0025 | -      -      -
Nestmeyer et al.                 | 0.2226 0.0046 0.0588 0.0018 0.3795 0.0078 | -      -      -
Pandey et al. (Total Relighting) | 0.0875 0.0007 0.0165 0.0003 0.2010 0.0022 | 0.1000 0.0252 0.2053
Hou et al. (CVPR'21)             | 0.1186 0.0013 0.0303 0.0006 0.2013 0.0023 | 0.1056 0.0247 0.1989
Hou et al. (CVPR'22)             | 0.0990 0.0013 0.0150 0.0004 0.1622 0.0017 | 0.1150 0.0238 0.2215
Ding et al. (DiffusionRig)       | 0.0870 0.0009 0.0098 0.0002 0.2098 0.0014 | 0.1130 0.0180 0.2292
Zhang et al. (IC-Light)          | 0.1978 0.0015 0.0499 0.0017 0.1887 0.0063 | 0.2239 0.0654 0.2102
Guo et al. (CVPR'25)             | 0.1088 0.0015 0.0234 0.0006 0.1733 0.0018 | 0.1230 0.0255 0.1869
DiFaReli                         | 0.0711 0.0011 0.0122 0.0005 0.1370 0.0020 | 0.0969 0.0215 0.1669
DiFaReli++                       | 0.0604 0.0010 0.0090 0.0003 0.1043 0.0013 | 0.0824 0.0169 0.1223
DiFaReli++_ss                    | 0.0590 0.0009 0.0075 0.0002 0.1023 0.0013 | 0.0801 0.0148 0.1123
"""


def _parse(text: str) -> dict[str, dict[str, tuple[tuple[float, float | None], ...]]]:
    out = {}
    for line in text.strip().splitlines():
        name, same, diff = (part.strip() for part in line.split("|"))
        v = [float(x) for x in same.split()]
        out[name] = {"same": tuple(zip(v[0::2], v[1::2]))}
        if diff.split()[0] != "-":
            out[name]["different"] = tuple((float(x), None) for x in diff.split())
    return out


#: method -> protocol ("same" (i) / "different" (ii)) -> ((DSSIM, SE), (MSE, SE), (LPIPS, SE)); SE None: unpublished
FIGURES: dict[str, dict[str, tuple[tuple[float, float | None], ...]]] = _parse(_PRINTED)
#: The paper's own three rows (what ``published=ours`` adds).
OURS = ("DiFaReli", "DiFaReli++", "DiFaReli++_ss")


def rows(methods: list[str] | None = None,
         protocols: list[str] | None = None) -> dict[tuple[str, str], dict[str, Stat]]:
    """``{(method, protocol): {metric: Stat}}`` of the published figures (``methods`` None: every row)."""
    unknown = sorted(set(methods or ()) - set(FIGURES))
    if unknown:
        raise UserError(f"no published Multi-PIE figures for {unknown}; choose from {list(FIGURES)}")
    out = {}
    for m in methods or list(FIGURES):
        for p, figs in FIGURES[m].items():
            if protocols is None or p in protocols:
                out[(m, p)] = {k: Stat(mean, math.nan if se is None else se, N[p])
                               for k, (mean, se) in zip(("dssim", "mse", "lpips"), figs)}
    return out


def add_to(table: Table, methods: list[str] | None = None) -> Table:
    """Append the published rows for ``table``'s protocols (labelled ``[published]``) to ``table``."""
    table.add_published(rows(methods, table.protocols or None), SOURCE)
    return table
