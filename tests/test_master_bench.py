"""`bench --json`'s `master`: the master's own cost per cycle on a line of virtual slaves
linked in this process, the slaves' time taken out (the figure is measured, not asserted:
what is checked is that it is a figure of the master alone)."""

from robot.bench import measure_master


def test_the_master_cost_leaves_the_virtual_slaves_out():
    result = measure_master(3, 200)
    assert result["joints"] == 3 and result["cycles"] == 200
    # positive and finite: the master did work; the slaves' time was measured apart
    assert 0 < result["master_median_us"] <= result["master_p99_us"] < 1e6
    assert result["virtual_slaves_median_us"] > 0
