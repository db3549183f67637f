"""difareli-app under a crowd: N relight requests at once, every connection answered and every answer right.

    python scripts/app_load.py [--checkpoint difareli_pp_ss-synth64] [--example astronaut] [--n 10 20 50]
        [--out load.json] [-- <more difareli-app overrides, e.g. server.queue=4>]

Starts ``difareli-app`` (port 0, its default ``server`` bounds) with the checkpoint, prepares one example photo
(``POST /api/source``), relights it once (the reconstruction is cached from then on), then relights it under
max(N) distinct light directions one at a time: the reference answers. Then, for each N, N threads send
``POST /api/relight`` at the same moment, each with its own light. Checked: every connection gets an HTTP answer
(a reset or a timeout is counted as "no answer"), each answer is 200 or 503 with ``Retry-After``, and every 200
equals its one-at-a-time answer byte for byte in everything but its ``seconds`` timings (the relit crop and photo,
the reconstruction error, the notes). Printed (and written to ``--out`` as JSON): per N, the counts, the wall
seconds of the burst, and the server's resident memory after it and at its peak (``VmRSS`` / ``VmHWM`` of its
process). Exit status 1 when a check fails.
"""

from __future__ import annotations

import argparse
import http.client
import json
import math
import os
import platform
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path


def cpu() -> str:
    """The CPU model and the cores this process may use."""
    try:
        model = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        model = platform.processor() or "unknown CPU"
    return f"{model}, {len(os.sched_getaffinity(0))} core(s)"


def memory_mib(pid: int) -> dict[str, float]:
    """The resident memory of process ``pid`` now and at its peak (MiB)."""
    status = Path(f"/proc/{pid}/status").read_text()
    return {k: int(re.search(rf"^{k}:\s+(\d+) kB", status, re.M).group(1)) / 1024 for k in ("VmRSS", "VmHWM")}


def post(port: int, path: str, body: dict, timeout: float = 600) -> tuple[int | None, dict, dict | str]:
    """(status, headers, JSON answer), or (None, {}, why) when the connection got no HTTP answer."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        conn.request("POST", path, body=json.dumps(body).encode(), headers={"Content-Type": "application/json"})
        r = conn.getresponse()
        return r.status, dict(r.getheaders()), json.loads(r.read())
    except (OSError, http.client.HTTPException) as e:  # reset, refused, timed out, cut answer
        return None, {}, f"{type(e).__name__}: {e}"
    finally:
        conn.close()


def lights(n: int) -> list[list[float]]:
    """``n`` distinct light directions on the front half of the sphere (a golden-angle spiral)."""
    out = []
    for i in range(n):
        z = 0.35 + 0.6 * (i + 0.5) / n
        r, a = math.sqrt(1 - z * z), i * math.pi * (3 - math.sqrt(5))
        out.append([round(r * math.cos(a), 6), round(r * math.sin(a), 6), round(z, 6)])
    return out


def start_app(checkpoint: str, extra: list[str]) -> tuple[subprocess.Popen, int, str]:
    """``difareli-app`` on a free port; returns the process, the port and its start-up line."""
    exe = Path(sys.executable).with_name("difareli-app")
    proc = subprocess.Popen([str(exe), f"checkpoint={checkpoint}", "port=0", *extra], stdout=subprocess.PIPE,
                            text=True)
    for line in proc.stdout:
        m = re.search(r"open http://[^:]+:(\d+)/", line)
        if m:
            threading.Thread(target=proc.stdout.read, daemon=True).start()  # keep its pipe drained
            return proc, int(m.group(1)), line.strip()
    raise SystemExit(f"difareli-app stopped before serving (exit {proc.wait()})")


def burst(port: int, sid: str, directions: list[list[float]]) -> tuple[list[tuple], float]:
    """All requests at once (a barrier releases the threads together); their answers and the wall seconds."""
    gate = threading.Barrier(len(directions))
    answers: list[tuple] = [()] * len(directions)

    def one(i: int) -> None:
        gate.wait()
        answers[i] = post(port, "/api/relight", {"id": sid, "light": {"kind": "direction", "direction": directions[i]}})

    threads = [threading.Thread(target=one, args=(i,)) for i in range(len(directions))]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return answers, time.perf_counter() - t0


def judge(answers: list[tuple], reference: list[dict]) -> dict:
    """Counts of the burst's answers and the problems found (an empty list: every check passed)."""
    out = {"n": len(answers), "ok": 0, "busy": 0, "no_answer": 0, "other": 0, "problems": []}
    for i, (status, headers, body) in enumerate(answers):
        if status is None:
            out["no_answer"] += 1
            out["problems"].append(f"request {i}: no HTTP answer ({body})")
        elif status == 200:
            out["ok"] += 1
            if {k: v for k, v in body.items() if k != "seconds"} != reference[i]:
                out["problems"].append(f"request {i}: its 200 differs from its one-at-a-time answer")
        elif status == 503 and headers.get("Retry-After", "").isdigit():
            out["busy"] += 1
            out.setdefault("retry_after", set()).add(int(headers["Retry-After"]))
        else:
            out["other"] += 1
            out["problems"].append(f"request {i}: HTTP {status} {str(body)[:200]}")
    out["retry_after"] = sorted(out.get("retry_after", ()))
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default="difareli_pp_ss-synth64")
    p.add_argument("--example", default="astronaut", help="the example photo (difareli.app.examples.EXAMPLES)")
    p.add_argument("--n", type=int, nargs="+", default=[10, 20, 50])
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("extra", nargs="*", help="difareli-app overrides (after --)")
    args = p.parse_args()
    proc, port, line = start_app(args.checkpoint, args.extra)
    report = {"cpu": cpu(), "app": line, "checkpoint": args.checkpoint, "example": args.example, "bursts": []}
    try:
        status, _, src = post(port, "/api/source", {"kind": "example", "name": args.example})
        if status != 200:
            raise SystemExit(f"POST /api/source answered {status}: {src}")
        directions = lights(max(args.n))
        post(port, "/api/relight", {"id": src["id"], "light": {"kind": "direction", "direction": [0, 0, 1]}})
        reference = []
        for d in directions:
            status, _, body = post(port, "/api/relight", {"id": src["id"], "light": {"kind": "direction",
                                                                                      "direction": d}})
            if status != 200:
                raise SystemExit(f"a one-at-a-time relight answered {status}: {body}")
            reference.append({k: v for k, v in body.items() if k != "seconds"})
        report["reference_mib"] = memory_mib(proc.pid)
        for n in args.n:
            answers, seconds = burst(port, src["id"], directions[:n])
            row = {**judge(answers, reference), "seconds": round(seconds, 2), **memory_mib(proc.pid)}
            report["bursts"].append(row)
            print(f"N={n}: {row['ok']} x 200 (each equal to its one-at-a-time answer: "
                  f"{'yes' if not row['problems'] else 'NO'}), {row['busy']} x 503 with Retry-After "
                  f"{row['retry_after']}, {row['no_answer']} without an answer, {row['other']} other; "
                  f"{seconds:.1f} s; server RSS {row['VmRSS']:.0f} MiB, peak {row['VmHWM']:.0f} MiB", flush=True)
            for problem in row["problems"][:5]:
                print(f"  {problem}")
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(60)
    print(f"CPU: {report['cpu']}; {report['app']}")
    if args.out:
        args.out.write_text(json.dumps(report, indent=1) + "\n")
    return 1 if any(b["problems"] for b in report["bursts"]) else 0


if __name__ == "__main__":
    sys.exit(main())
