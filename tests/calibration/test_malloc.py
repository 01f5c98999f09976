"""The allocator setting the frfcal command applies before large dense work (frfcal/_malloc.py)."""

import platform
import resource
import sys

import numpy as np
import pytest

from frfcal._malloc import keep_large_allocations

glibc = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"


@pytest.mark.skipif(not glibc, reason="mallopt settings exist on glibc only")
def test_large_temporaries_are_reused_not_faulted_in_again():
    assert keep_large_allocations() is True
    n = 8_000_000  # 64 MB, above glibc's default mmap ceiling of 32 MiB
    pages = n * 8 // resource.getpagesize()
    np.ones(n).sum()  # first use may fault the pages in
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
        assert np.ones(n).sum() == n
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    # default glibc: a fresh mapping each time (measured ~3000 faults here, numpy asks for
    # huge pages); kept in the heap: 0
    assert faults < pages // 100, f"{faults} page faults for 10 reuses of {pages} pages"


@pytest.mark.skipif(glibc, reason="checks the no-op on other C libraries")
def test_elsewhere_it_does_nothing():
    assert keep_large_allocations() is False
