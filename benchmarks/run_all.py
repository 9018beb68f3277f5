"""Run every benchmark script in this folder but the soak test (``bench_soak.py``), one after another,
then ``evseg evaluate labelled`` on the synthetic probe scenes of ``../shared/data/synthetic_probe``
(``make bench``)."""

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
PROBE = HERE.parents[1] / "shared" / "data" / "synthetic_probe"
# Scripts that take too long for ``make bench``: the soak test runs for a quarter of an hour.
ON_THEIR_OWN = {"bench_soak.py"}


def probe_scenes() -> int:
    """Score the default config on the probe scenes; 0 when they are absent."""
    scenes = sorted(PROBE.glob("*.npz"))
    if not scenes:
        print(f"skipped: no probe scenes in {PROBE}")
        return 0
    command = ["evaluate", "labelled", *map(str, scenes)]
    return subprocess.run([sys.executable, "-m", "evseg_torch.app.cli", "--quiet", *command]).returncode


if __name__ == "__main__":
    failed = []
    for script in sorted(HERE.glob("bench_*.py")):
        if script.name in ON_THEIR_OWN:
            continue
        print(f"\n=== {script.name}", flush=True)
        if subprocess.run([sys.executable, str(script)]).returncode != 0:
            failed.append(script.name)
    print("\n=== evseg evaluate labelled (synthetic probe scenes)", flush=True)
    if probe_scenes() != 0:
        failed.append("evaluate labelled")
    sys.exit(f"failed: {', '.join(failed)}" if failed else 0)
