"""vggt_init.memory: freed memory stays in the process (glibc), so re-allocating a large
buffer causes no page faults; the environment switch and the CLI flag turn it off.

Each check runs in a subprocess: the malloc settings are process-wide. Page-fault counts
are exact kernel counters (ru_minflt). With torch's huge-page allocation on (vggt_init's
default) a 64 MB buffer that is faulted in anew costs at least 32 faults (2 MB pages; 16384
where the kernel falls back to 4 kB pages), a reused one none.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                                reason="the malloc settings exist only in glibc")

FIX = Path(__file__).parent / "data" / "vggt" / "shared"

_SCRIPT = textwrap.dedent("""
    import json, resource, sys
    from vggt_init.memory import memory_retained, retain_freed_memory
    applied = retain_freed_memory() if sys.argv[1] == "retain" else False
    import torch
    faults = []
    for _ in range(3):
        f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        x = torch.empty(16 * 2**20, dtype=torch.float32)  # 64 MB
        x.fill_(1.0)
        del x
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
    print(json.dumps({"applied": applied, "retained": memory_retained(), "faults": faults}))
""")


def _run(mode: str, **env: str) -> dict:
    full_env = {k: v for k, v in os.environ.items() if k != "VGGT_INIT_RETAIN_MEMORY"}
    full_env.update(THP_MEM_ALLOC_ENABLE="1", **env)
    res = subprocess.run([sys.executable, "-c", _SCRIPT, mode], capture_output=True, text=True, env=full_env,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_retained_memory_is_reused_without_page_faults():
    default = _run("default")
    retained = _run("retain")
    assert default["applied"] is False and retained["applied"] is True and retained["retained"] is True
    # glibc's own behaviour: a 64 MB block is mmap'd and unmapped each time -> faulted in anew
    assert min(default["faults"][1:]) >= 32, default
    # retained: the first round faults the heap in, later rounds reuse it
    assert retained["faults"][0] >= 32, retained
    assert max(retained["faults"][1:]) <= 4, retained


def test_environment_switch_turns_it_off():
    off = _run("retain", VGGT_INIT_RETAIN_MEMORY="0")
    assert off["applied"] is False and off["retained"] is False
    assert min(off["faults"][1:]) >= 32, off


def test_cli_applies_it_and_records_it(tmp_path):
    """The vggt_init CLI turns it on (in its own process) and says so in timing.json."""
    from _oiio_write import write_raw

    import numpy as np

    images = tmp_path / "images"
    images.mkdir()
    yy, xx = np.mgrid[0:40, 0:60]
    for i in range(2):
        write_raw(images / f"im{i}.png", np.stack([xx * 4 + i, yy * 6, (xx + yy) * 2], -1).clip(0, 255).astype(np.uint8))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "vggt_init", "--images", str(images), "--out", str(out),
           "--model-config", str(FIX / "config.json"), "--checkpoint", str(FIX / "weights.safetensors"),
           "--image-size", "56", "--threads", "1", "--max-points", "100", "-q"]
    env = {k: v for k, v in os.environ.items() if k != "VGGT_INIT_RETAIN_MEMORY"}
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    assert json.loads((out / "timing.json").read_text())["retain_freed_memory"] is True
