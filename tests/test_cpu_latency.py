"""The real-time processes keep the CPUs out of sleep states (PM QoS, /dev/cpu_dma_latency):
the request holds while its descriptor is open and ends with it, and a refusal is a reason,
not an error."""

import os

import pytest

from driver.clock import CPU_DMA_LATENCY, cpus_awake


def _current_latency_us() -> int:
    """The kernel's aggregate request (reading the device gives it as a native s32)."""
    with open(CPU_DMA_LATENCY, "rb") as device:
        return int.from_bytes(device.read(4), "little", signed=True)


@pytest.mark.root
@pytest.mark.skipif(os.geteuid() != 0 or not os.path.exists(CPU_DMA_LATENCY),
                    reason="needs root and /dev/cpu_dma_latency")
@pytest.mark.real_time
def test_the_request_holds_while_inside_and_ends_after():
    before = _current_latency_us()
    if before == 0:
        pytest.skip("another process holds a request of 0 already: nothing to see here")
    with cpus_awake() as refused:
        assert refused is None
        assert _current_latency_us() == 0
    assert _current_latency_us() == before


def test_a_refused_request_says_why(monkeypatch):
    monkeypatch.setattr("driver.clock.CPU_DMA_LATENCY", "/nonexistent/cpu_dma_latency")
    with cpus_awake() as refused:
        assert refused and "No such file" in refused
