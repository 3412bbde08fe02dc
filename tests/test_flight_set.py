"""benchmarks.flight_set: a set of lying-model replays, resumable, with issue 13's goals pooled."""
from __future__ import annotations

import json

import pytest

from edge_landing.benchmarks import flight_set as fs

pytest.importorskip("embreex")


def _row(name: str, frames: int, **models: tuple[int, int, int, int]) -> dict:
    row: dict = {"flight": name, "frames": frames}
    for m, (sent, safe, net, net_safe) in models.items():
        row[m] = {"sent": sent, "sent_safe": safe, "network": net, "network_safe": net_safe}
    return row


def test_goals_pool_the_flights_and_name_the_unsafe_ones():
    rows = [_row("a", 200, lying=(180, 180, 200, 120), shipped=(150, 150, 140, 130)),
            _row("b", 200, lying=(39, 30, 200, 90), shipped=(0, 0, 20, 20))]
    g = fs.goals(rows)
    lying, shipped = g["lying"], g["shipped"]
    assert (lying["sent"], lying["sent_safe"], lying["network_alone_safe"]) == (219, 210, 210)
    assert lying["safe_met"] == (210 >= 0.95 * 219)          # 95.9 %: met
    assert lying["flights_with_enough_targets"] == 1 and not lying["frames_met"]   # 39 < 20 % of 200
    assert lying["unsafe_flights"] == ["b"]
    assert shipped["safe_met"] and shipped["flights_at_least_network"] == 1
    text = fs.report(rows, g)
    assert "unsafe targets on b" in text and "NOT met" in text


def test_the_network_alone_as_edge_run_sends_it_is_pooled_beside_the_raw_count():
    rows = [_row("a", 200, shipped=(150, 150, 160, 140)), _row("b", 200, shipped=(90, 90, 120, 100)),
            _row("old", 200, shipped=(10, 10, 50, 50))]          # written before network_sent existed
    rows[0]["shipped"].update(network_sent=140, network_sent_safe=130)
    rows[1]["shipped"].update(network_sent=95, network_sent_safe=95)
    g = fs.goals(rows)["shipped"]
    assert g["flights_at_least_network"] == 0
    assert g["network_sent"] == {"flights": 2, "targets": 235, "safe": 225, "flights_at_least": 1}
    text = fs.report(rows, {"shipped": g})
    assert "as sent 140, safe 130" in text and "at least its count on 1" in text
    assert "network_sent" not in fs.goals(rows[2:])["shipped"]


def test_nothing_sent_does_not_meet_the_safety_goal():
    g = fs.goals([_row("a", 200, lying=(0, 0, 200, 100))])["lying"]
    assert g["safe_share"] is None and not g["safe_met"] and not g["frames_met"]


@pytest.mark.parametrize("text", ["forest:1", "suburban", "suburban:-3", "urban:7:sideways", "urban:x"])
def test_bad_flight_names_are_one_line_exit_2(text, tmp_path, capsys):
    assert fs.main(["--flights", text, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--flights" in err[0]


def test_validation_set_is_42_flights_of_both_styles():
    flights = fs.validation_set("arc")
    assert len(flights) == len(set(flights)) == 42
    assert {f.style for f in flights} == {"suburban", "urban"} and {f.approach for f in flights} == {"arc"}


def test_a_short_set_is_written_reused_and_refused_with_other_settings(tmp_path, capsys):
    out = tmp_path / "set"
    args = ["--flights", "suburban:5150", "--frames", "12", "--workers", "1", "--out", str(out)]
    assert fs.main(args) == 0
    first = capsys.readouterr().out
    path = out / "suburban_5150_straight.json"
    result = json.loads(path.read_text())
    st = result["stats"]["lying"]
    assert result["frames"] == 12 and 0 <= st["sent"]["safe"] <= st["sent"]["targets"] <= 12
    assert st["network"]["targets"] == 12      # the lying network always has a spot
    # ... which edge-run --allow-unconfirmed sends only through the continuity (cone, commitment)
    assert 0 <= st["network_sent"]["safe"] <= st["network_sent"]["targets"] <= 12
    summary = json.loads((out / "summary.json").read_text())
    assert summary["flights"][0]["lying"]["sent"] == st["sent"]["targets"]
    assert summary["flights"][0]["lying"]["network_sent"] == st["network_sent"]["targets"]
    assert "[1/1] suburban_5150_straight" in first
    # The weather the sim drew for the flight, as its renderer used it (one draw per flight), in the row and the report.
    from edge_landing import sim
    from edge_landing.sim.generate import SimConfig, frame_effects
    drawn = frame_effects(SimConfig(out=tmp_path, frames=12, style=sim.Style.from_string("suburban"), seed=5150,
                                    flight=True), 0)
    weather = summary["flights"][0]["weather"]
    assert weather == result["weather"] == drawn.to_json() and weather["rain"] == round(drawn.rain, 6)
    assert weather["noise_sigma"] == round(drawn.noise_sigma, 6) and 0.0 <= weather["noise_sigma"] <= 0.03
    assert f"sensor noise {drawn.noise_sigma:.3f}" in first
    stamp = path.stat().st_mtime_ns
    assert fs.main(args) == 0                # reused, not flown again
    assert path.stat().st_mtime_ns == stamp and "[1/1]" not in capsys.readouterr().out
    assert fs.main(["--flights", "suburban:5150", "--frames", "14", "--out", str(out)]) == 2
    assert "other settings" in capsys.readouterr().err
