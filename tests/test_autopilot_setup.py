"""The autopilot's precision-landing setup (runtime/io/autopilot_setup.py): read over MAVLink, held when wrong.

The state is tested alone; the link against the fake autopilot (a TEST DOUBLE answering PARAM_REQUEST_READ as
ArduPilot's GCS_Param.cpp does), with edge-run's own command line and real pymavlink on both ends.
"""
from __future__ import annotations

import logging

import pytest

from edge_landing.cli.run import main
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.io.autopilot_setup import AutopilotSetup, SetupCheck, SetupConfig
from edge_landing.runtime.pipeline.stats import RunSummary
from tests.fake_autopilot import PRECLAND_PARAMS, FakeAutopilot
from tests.run_helpers import flat_assets, free_udp_port, read_decisions

AGL_M = 10.0


def _read(setup: AutopilotSetup, **changes: float) -> AutopilotSetup:
    for name, value in {**PRECLAND_PARAMS, **changes}.items():
        setup.on_value(name, value)
    return setup


def test_a_right_setup_holds_nothing_and_says_so():
    setup = AutopilotSetup()
    assert setup.hold_reason(0.0).startswith("held: reading the autopilot's precision-landing setup (PLND_ENABLED")
    _read(setup)
    assert setup.read_all() and setup.problems() == [] and setup.hold_reason(0.0) == ""
    assert setup.describe().endswith("LANDING_TARGET is used as edge-run sends it")
    assert "PLND_ORIENT=25" in setup.describe() and setup.value("PLND_LAG") == pytest.approx(0.02)


@pytest.mark.parametrize("name, value, held", [("PLND_ORIENT", 0.0, True), ("PLND_YAW_ALIGN", 9000.0, True),
                                               ("PLND_ENABLED", 0.0, False), ("PLND_TYPE", 2.0, False)])
def test_a_setting_that_turns_the_direction_holds_one_that_ignores_targets_warns(name, value, held):
    setup = _read(AutopilotSetup(), **{name: value})
    [problem] = setup.problems()
    assert problem.rule.name == name and f"{name} is {value:g}" in problem.line
    assert len(f"{problem.short}: edge targets held") <= 50          # what the ground station's STATUSTEXT shows
    assert bool(setup.hold_reason(0.0)) == held
    if held:
        assert setup.hold_reason(0.0).startswith(f"held: the autopilot's {name} is {value:g}")
    assert not _read(AutopilotSetup(SetupConfig(SetupCheck.WARN)), **{name: value}).hold_reason(0.0)


def test_a_change_applied_at_boot_holds_until_the_autopilot_reboots():
    setup = _read(AutopilotSetup(), PLND_ORIENT=0.0)
    assert "PLND_ORIENT is 0" in setup.hold_reason(0.0)
    setup.on_value("PLND_ORIENT", 25.0)           # set from a ground station: ArduPilot broadcasts it
    assert "changed from 0 to 25 since the autopilot booted" in setup.hold_reason(0.0)
    assert setup.value("PLND_ORIENT") == 0.0      # what the autopilot still runs with
    setup.restarted()
    assert setup.hold_reason(0.0).startswith("held: reading") and not setup.read_all()
    _read(setup)
    assert setup.hold_reason(0.0) == "" and setup.value("PLND_ORIENT") == 25.0
    # PLND_YAW_ALIGN applies at once: a change is simply the new value.
    setup.on_value("PLND_YAW_ALIGN", 4500.0)
    assert "PLND_YAW_ALIGN is 4500" in setup.hold_reason(0.0)
    setup.on_value("PLND_YAW_ALIGN", 0.0)
    assert setup.hold_reason(0.0) == ""


def test_requests_are_repeated_a_few_times_then_given_up():
    setup = AutopilotSetup(SetupConfig(retry_s=1.0, attempts=3))
    assert len(setup.due(0.0)) == 5 and setup.due(0.5) == []
    setup.on_value("PLND_ENABLED", 1.0)
    setup.on_value("NOT_OURS", 3.0)               # another parameter (a ground station's download) is ignored
    assert "PLND_ENABLED" not in setup.due(1.0) and len(setup.due(2.0)) == 4
    assert setup.hold_reason(0.9).startswith("held: reading")    # until read, or read_wait_s after the first ask
    assert setup.hold_reason(1.0) == ""
    assert setup.due(2.5) == [] and setup.given_up() == []
    assert setup.due(3.0) == [] and set(setup.given_up()) == set(PRECLAND_PARAMS) - {"PLND_ENABLED"}
    assert setup.hold_reason(3.0) == ""              # nothing wrong read: nothing to hold on
    report = setup.report()
    assert report["values"] == {"PLND_ENABLED": 1.0} and len(report["unanswered"]) == 4


def test_the_summary_compares_plnd_lag_with_the_latency_measured():
    s = RunSummary()
    for _ in range(5):
        s.times.add("pose_to_send", 0.12)
        s.times.add("capture_to_send", 0.15)
    assert "set PLND_LAG = 0.12" in s.plnd_lag_line()
    s.autopilot_setup = _read(AutopilotSetup()).report()
    assert "the autopilot has PLND_LAG = 0.02: set 0.12" in s.plnd_lag_line()
    s.autopilot_setup = _read(AutopilotSetup(), PLND_LAG=0.11).report()
    assert "PLND_LAG = 0.11 matches it" in s.plnd_lag_line()
    assert s.setup_lines()[0].startswith("autopilot setup (hold): PLND_ENABLED=1 PLND_TYPE=1 PLND_ORIENT=25")


def test_a_bad_check_value_is_one_line():
    with pytest.raises(InputError, match="--autopilot-check 'maybe'"):
        SetupCheck.from_string("maybe")


# -- against the fake autopilot --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    return flat_assets(tmp_path_factory.mktemp("setup"), AGL_M)


def _run(assets, tmp_path, script, duration_s: float, params=None, *extra: str):
    port = free_udp_port()
    log_path = tmp_path / "decisions.jsonl"
    with FakeAutopilot(port, script) as fake:
        if params is not None:
            fake.params = params
        assert main(["--camera", assets["video"], "--model", assets["model"], "--loop", "--duration", str(duration_s),
                     "--mav", f"udpout:127.0.0.1:{port}", "--log", str(log_path), "--allow-unconfirmed", *extra]) == 0
    return fake, read_decisions(log_path)


def test_a_wrong_orientation_holds_every_target_until_fixed_and_rebooted(assets, tmp_path, capsys):
    def script(fake: FakeAutopilot, t: float) -> None:
        if 2.5 <= t < 2.55 and fake.params["PLND_ORIENT"] != 25.0:
            fake.set_param("PLND_ORIENT", 25.0)
        if 4.0 <= t < 4.05 and fake.boot_ms() > 3000:
            fake.reboot()
        fake.healthy()

    fake, decisions = _run(assets, tmp_path, script, 7.0, {**PRECLAND_PARAMS, "PLND_ORIENT": 0.0})
    requests = fake.of_type("PARAM_REQUEST_READ")
    assert {m.param_id for _, m in requests} == set(PRECLAND_PARAMS)
    assert all((m.target_system, m.target_component) == (1, 1) for _, m in requests)
    assert fake.targets_between(0.0, 4.0) == [], "no target may leave while ArduPilot would turn it again"
    reasons = [d["not_sent_because"] for d in decisions if d["valid"] and not d["sent"]]
    assert any(r.startswith("held: the autopilot's PLND_ORIENT is 0") for r in reasons)
    assert any("changed from 0 to 25 since the autopilot booted" in r for r in reasons)
    assert "PLND_ORIENT 0 not 25: edge targets held" in fake.texts()
    after = fake.targets_between(5.0, 1e9)
    assert len(after) >= 5, "after the reboot the setup is right and targets flow"
    assert all(t.frame == 12 and t.z == pytest.approx(AGL_M, abs=0.3) for t in after)
    out = capsys.readouterr().out
    assert "autopilot setup (hold): PLND_ENABLED=1 PLND_TYPE=1 PLND_ORIENT=25" in out


def test_warn_sends_and_an_autopilot_that_does_not_answer_is_said(assets, tmp_path, caplog):
    with caplog.at_level(logging.INFO):
        fake, _ = _run(assets, tmp_path, lambda f, t: f.healthy(), 3.0, {**PRECLAND_PARAMS, "PLND_YAW_ALIGN": 9000.0},
                       "--autopilot-check", "warn")
    assert len(fake.targets_between(0.0, 1e9)) >= 5
    assert any("PLND_YAW_ALIGN is 9000" in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.INFO):
        fake, _ = _run(assets, tmp_path, lambda f, t: f.healthy(), 6.5, {})   # answers no PARAM_REQUEST_READ
    assert len(fake.targets_between(0.0, 1e9)) >= 5
    assert any("did not answer for PLND_ENABLED" in r.getMessage() for r in caplog.records)
    assert len(fake.of_type("PARAM_REQUEST_READ")) == 5 * 5, "each name asked 5 times, then given up"
