"""jaxelastic.solvers.host.heap: freed heap memory back to the operating system."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from jaxelastic.solvers.host import heap


def test_release_free_memory_returns_bool():
    assert isinstance(heap.release_free_memory(), bool)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_map_large_blocks_returns_freed_blocks_at_once():
    """In a fresh process: every other one of 64 blocks of 4 MiB freed (holes between
    live blocks) stays resident with the default (dynamic) threshold; with
    ``map_large_blocks`` the freed blocks leave the resident set at once."""
    code = textwrap.dedent(
        """
        import sys
        import numpy as np
        from jaxelastic.solvers.host import heap

        def rss():
            for line in open("/proc/self/status"):
                if line.startswith("VmRSS"):
                    return int(line.split()[1]) / 1024

        if sys.argv[1] == "map" and not heap.map_large_blocks(1 << 20):
            print("unsupported")
            sys.exit()
        # a first freed 4 MB block raises glibc's dynamic threshold above 4 MB
        np.ones(4 << 17).sum()
        blocks = [np.ones(4 << 17) for _ in range(64)]  # 64 x 4 MiB, touched
        before = rss()
        del blocks[::2]  # 32 holes of 4 MiB, each between live blocks
        print(before - rss())
        """
    )

    def freed(mode):
        out = subprocess.run(
            [sys.executable, "-c", code, mode], capture_output=True, text=True, check=True
        )
        if out.stdout.strip() == "unsupported":
            pytest.skip("no glibc mallopt")
        return float(out.stdout.split()[-1])

    assert freed("map") > 100  # MiB of the 128 freed left the resident set at once
    assert freed("default") < 30  # kept by the arena (what the setting is for)
