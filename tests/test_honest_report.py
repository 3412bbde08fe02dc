"""benchmarks.honest_report: the scene specs it accepts and the edge-sim flags they turn into."""
import pytest

from edge_landing.benchmarks import honest_report
from edge_landing.runtime.core.errors import InputError


@pytest.mark.parametrize("spec", ["rural", "rural:x", "rural:901:fog", "rural:901:hazards:hazards", ":901"])
def test_bad_scene_specs_fail_with_the_spec_named(tmp_path, spec):
    with pytest.raises(InputError, match="--scene must be"):
        honest_report.scene_folder(tmp_path, spec, 4)


def test_scene_flags_become_edge_sim_flags_and_existing_scenes_are_kept(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(honest_report, "_tool", lambda module, *args: calls.append(args))
    folder = honest_report.scene_folder(tmp_path, "urban:941:randomise:hazards", 4)
    assert folder == tmp_path / "urban_941_randomise_hazards"
    assert calls and calls[0][calls[0].index("--seed") + 1] == "941"
    assert "--randomise" in calls[0] and "--hazards" in calls[0] and "--frames" in calls[0]
    (tmp_path / "rural_903").mkdir()
    (tmp_path / "rural_903" / "scene.json").write_text("{}")
    calls.clear()
    assert honest_report.scene_folder(tmp_path, "rural:903", 4) == tmp_path / "rural_903"
    assert calls == []                                    # rendered scenes are reused, not rendered again
