"""The report says how often the tracker's 95 % bound held the network's Table 2 errors."""

from biopsynav.report.sections import bound_coverage


def test_the_bound_coverage_counts_the_network_records_with_a_bound():
    records = [{"method": "net", "tre_mm": 0.2, "bound_mm": 0.5},
               {"method": "net", "tre_mm": 0.9, "bound_mm": 0.5},
               {"method": "net", "tre_mm": None, "bound_mm": None},  # refused push
               {"method": "fem", "tre_mm": 0.1, "bound_mm": 0.5},
               {"method": "net", "tre_mm": 0.3, "bound_mm": float("nan")}]
    text = bound_coverage(records)
    assert "within it in 1 of 2 pushes" in text and "mean bound 0.50 mm" in text
    assert bound_coverage([{"method": "net", "tre_mm": 0.2}]) == ""  # tables made before
