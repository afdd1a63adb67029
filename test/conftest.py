"""Test-wide settings: isolate DDS traffic of each test run from any other on the machine."""

import os
import random

import pytest

# Set before rclpy is imported anywhere: a private domain and localhost-only discovery, so two test
# runs (or a developer's robot) on one machine never see each other's topics.
os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(1, 100)))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
os.environ.setdefault('MPLBACKEND', 'Agg')


@pytest.fixture(scope='session', autouse=True)
def _one_blas_thread():
    """Run every test with BLAS on one thread, as the CLI does (core.parallel.one_blas_thread)."""
    from skidkin_ros.core.parallel import one_blas_thread

    with one_blas_thread():
        yield


@pytest.fixture
def make_rig():
    """Build in-process node rigs (real rclpy, real DDS) and close them after the test."""
    from node_harness import NodeRig  # imports rclpy: only for the tests that use it

    rigs = []

    def factory(overrides=None, params_file=None):
        rig = NodeRig(overrides, params_file)
        rigs.append(rig)
        return rig

    yield factory
    for rig in rigs:
        rig.close()
