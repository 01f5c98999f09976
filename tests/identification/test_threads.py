"""The identification's BLAS thread rule (docs/identification.md, "Threads")."""

import numpy as np
import pytest

threadpoolctl = pytest.importorskip("threadpoolctl")

from identification._identify import ONE_THREAD_BELOW_LINES, _one_blas_thread  # noqa: E402


def _blas_threads_seen(n_lines):
    @_one_blas_thread
    def probe(freq_hz):
        return max(i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas")

    return probe(np.linspace(1.0, 100.0, n_lines))


def test_short_data_run_on_one_blas_thread_and_long_data_keep_the_process_setting():
    outside = max(i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas")
    assert _blas_threads_seen(800) == 1
    assert _blas_threads_seen(ONE_THREAD_BELOW_LINES) == outside
    # the limit ends with the call
    assert max(i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas") == outside
