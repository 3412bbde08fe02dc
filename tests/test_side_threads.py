"""edge-run caps OpenCV's and BLAS's own thread pools (runtime/pipeline/threads.py)."""
import cv2
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from edge_landing.runtime.pipeline.threads import SideThreads, limit_side_threads


@pytest.fixture
def restore_threads():
    cv_before = cv2.getNumThreads()
    with threadpool_limits(limits=None):   # restores the BLAS pools on exit
        yield
    cv2.setNumThreads(cv_before)


def test_limit_side_threads_caps_opencv_and_blas(restore_threads):
    limit_side_threads(SideThreads(opencv=1, blas=1))
    assert cv2.getNumThreads() == 1
    blas = [p for p in threadpool_info() if p["user_api"] == "blas"]
    assert blas, "numpy should load a BLAS library"
    assert all(p["num_threads"] == 1 for p in blas)


def test_zero_leaves_a_library_alone(restore_threads):
    cv2.setNumThreads(2)
    limit_side_threads(SideThreads(opencv=0, blas=0))
    assert cv2.getNumThreads() == 2
