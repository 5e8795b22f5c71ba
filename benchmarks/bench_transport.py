"""Large clouds over DDS: Fast DDS defaults vs the large-data profile in the mapper only vs
in every process, VLP-16-sized clouds (28.8k points, about 0.6 MB) at 10 Hz over loopback.

    .venv/bin/python benchmarks/bench_transport.py                 # 2 rounds of 15 s each
    .venv/bin/python benchmarks/bench_transport.py --rounds 3 --duration 20

Each run is ``benchmarks/bench_node.py --stream vlp16 --dds {none,mapper,all}`` in a process
of its own (a process reads its Fast DDS profile once, when its first participant starts);
the three settings are interleaved round by round, so machine load hits them alike. Per
setting: clouds sent, lost in transport (the node's ``clouds_lost_transport``: the
middleware's sample-lost counts), received, integrated, dropped by the node (by reason),
summed over the rounds.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SETTINGS = {
    "none": "Fast DDS defaults everywhere",
    "mapper": "profile in the mapper only",
    "all": "profile in every process",
}


def run(dds: str, duration: float, out: Path) -> dict:
    """One bench_node run; its vlp16 result."""
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_node.py"), "--stream", "vlp16"]
    cmd += ["--duration", str(duration), "--dds", dds, "--json", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, check=False)
    if done.returncode != 0 or not out.is_file():
        raise RuntimeError(f"bench_node --dds {dds} failed:\n{done.stdout[-2000:]}{done.stderr}")
    return json.loads(out.read_text())[0]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--duration", type=float, default=15.0, help="seconds per run")
    args = parser.parse_args()
    totals = {dds: Counter() for dds in SETTINGS}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.rounds):
            for dds in SETTINGS:
                r = run(dds, args.duration, Path(tmp) / f"{dds}{k}.json")
                t = totals[dds]
                for key in ("clouds_sent", "clouds_received", "clouds_lost_in_transport"):
                    t[key] += r[key]
                t["clouds_integrated"] += r["clouds_integrated"]
                for reason, n in r["clouds_dropped"].items():
                    t[f"dropped {reason}"] += n
                print(
                    f"round {k + 1} {dds:<6}: {json.dumps(r['clouds_dropped'])} "
                    f"{r['clouds_integrated']}/{r['clouds_sent']} integrated, "
                    f"{r['clouds_lost_in_transport']} lost in transport",
                    flush=True,
                )
    print(f"\n{args.rounds} x {args.duration:.0f} s of VLP-16 clouds at 10 Hz, loopback")
    print("| setting | sent | lost in transport | received | integrated | dropped by the node |")
    print("|---|---|---|---|---|---|")
    for dds, label in SETTINGS.items():
        t = totals[dds]
        drops = ", ".join(
            f"{k.split(' ', 1)[1]} {v}" for k, v in sorted(t.items()) if k.startswith("dropped")
        )
        print(
            f"| {label} | {t['clouds_sent']} | {t['clouds_lost_in_transport']} | "
            f"{t['clouds_received']} | {t['clouds_integrated']} | {drops or 'none'} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
