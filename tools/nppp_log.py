"""Runs `nppp render` for the measurement tools in tools/ and reads its log.
Standard library only; not part of the pipeline or of `make test`."""

import re
import subprocess
import sys

# " in 2.84s (scene build 0.37s)": the render's time, pilot included.
TIME = re.compile(r" in ([0-9.]+)s \(scene build")


def render_log(cmd, *patterns):
    """Runs `cmd`, exits naming it if it fails, and returns its log (stderr)
    and the match of each regular expression in `patterns` on it, exiting if
    one has no match."""
    run = subprocess.run(cmd, capture_output=True, text=True)
    if run.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{run.stderr}")
    found = [p.search(run.stderr) for p in patterns]
    if not all(found):
        sys.exit(f"cannot read the output of {' '.join(cmd)}:\n{run.stderr}")
    return run.stderr, found
