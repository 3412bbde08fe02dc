"""edge-run's choice of model file: the FP32 file or its INT8 twin, probed on this CPU and cached."""
import json
from pathlib import Path

import pytest

pytest.importorskip("onnx")

from edge_landing.cli.common import EXIT_BAD_INPUT
from edge_landing.cli.run import choose_files, config_from_args, main
from edge_landing.export.quantize import QuantizeConfig, quantize
from edge_landing.runtime.core import cpu_features as cf
from edge_landing.runtime.core.errors import InputError
from edge_landing.runtime.perception import precision as pr
from edge_landing.runtime.perception.contract import Task
from tests.quant_models import textured_scene, tiny_conv_net

X86_NO_VNNI = "processor\t: 0\nmodel name\t: AMD EPYC 7B12\nflags\t\t: fpu sse2 avx fma avx2 bmi2\n\n" \
              "processor\t: 1\nmodel name\t: AMD EPYC 7B12\nflags\t\t: fpu sse2 avx fma avx2 bmi2\n"
ARM = "processor\t: 0\nBogoMIPS\t: 50.00\nFeatures\t: fp asimd evtstrm aes crc32 atomics asimddp i8mm\n"


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """A tiny FP32 net, its gate-passing INT8 twin, and a copy whose INT8 twin failed the gate (--force)."""
    d = tmp_path_factory.mktemp("precision")
    fp32 = tiny_conv_net(d / "net.onnx", Task.DEPTH_HVO, height=64, width=96)
    scene = textured_scene(d / "scene", 8, height=64, width=96)
    report = quantize(fp32, d / "net.int8.onnx", QuantizeConfig(calib_scene=scene, calib_frames=5, eval_frames=3,
                                                                progress=False, speed_gate=False))
    assert report.passed and report.written
    bad_dir = d / "bad"
    bad_dir.mkdir()
    bad = tiny_conv_net(bad_dir / "net.onnx", Task.DEPTH_HVO, height=64, width=96)
    black = textured_scene(d / "black", 10, height=64, width=96, black_first=6)
    failed = quantize(bad, bad_dir / "net.int8.onnx", QuantizeConfig(calib_scene=black, calib_frames=6, eval_frames=4,
                                                                     progress=False, force=True, speed_gate=False))
    assert failed.written and not failed.passed
    return {"fp32": fp32, "int8": d / "net.int8.onnx", "bad": bad}


def _probe(tmp_path):
    return pr.ProbeConfig(threads=1, warmup=1, iterations=5, cache_dir=tmp_path / "cache")


def test_cpu_flags_are_read_for_x86_without_vnni_and_arm_dot_product():
    model, feats = cf.parse_cpuinfo(X86_NO_VNNI)
    assert model == "AMD EPYC 7B12" and feats == ("AVX2", "FMA")
    assert not cf.CpuFeatures(model, "x86_64", feats, "test").int8_dot_product
    _, arm = cf.parse_cpuinfo(ARM)
    assert arm == ("ARM-DOTPROD", "ARM-I8MM")
    assert cf.CpuFeatures("", "aarch64", arm, "test").int8_dot_product
    here = cf.cpu_features()
    assert here.source and here.summary().startswith(here.model)


def test_auto_probes_once_then_reads_the_cache(pair, tmp_path, monkeypatch):
    first = pr.pick_model(pair["fp32"], pr.Precision.AUTO, _probe(tmp_path))
    assert first.precision in (pr.Precision.FP32, pr.Precision.INT8) and "probed now" in first.reason
    assert first.path == (pair["int8"] if first.precision is pr.Precision.INT8 else pair["fp32"])
    files = list((tmp_path / "cache").glob("precision-*.json"))
    assert len(files) == 1
    record = json.loads(files[0].read_text())
    assert record["fp32_p50_s"] > 0 and record["int8_p50_s"] > 0 and record["cpu"]["features"] == list(
        cf.cpu_features().features)

    def no_probe(*_):
        raise AssertionError("probed although the verdict is cached")

    monkeypatch.setattr(pr, "probe", no_probe)
    again = pr.pick_model(pair["fp32"], pr.Precision.AUTO, _probe(tmp_path))
    assert again.path == first.path and "cached" in again.reason and "probed" not in again.reason


def test_the_cache_is_per_cpu_and_a_broken_entry_is_probed_again(pair, tmp_path, monkeypatch):
    pr.pick_model(pair["fp32"], pr.Precision.AUTO, _probe(tmp_path))
    (entry,) = (tmp_path / "cache").glob("precision-*.json")
    entry.write_text("{not json")
    assert "probed now" in pr.pick_model(pair["fp32"], pr.Precision.AUTO, _probe(tmp_path)).reason
    other = cf.CpuFeatures("AMD EPYC 7B12", "x86_64", ("AVX2", "FMA"), "test")
    monkeypatch.setattr(pr, "cpu_features", lambda: other)
    choice = pr.pick_model(pair["fp32"], pr.Precision.AUTO, _probe(tmp_path))
    assert "probed now" in choice.reason and "AVX2 FMA" in choice.reason
    assert len(list((tmp_path / "cache").glob("precision-*.json"))) == 2


def test_auto_keeps_fp32_where_the_recorded_probe_says_int8_is_slower(pair, tmp_path):
    # The cache entry of a CPU where INT8 ran slower (the AVX2-only EPYC: 0.68x): the same decision
    # path as after a real probe, with that CPU's ratio.
    config = _probe(tmp_path)
    key = pr.cache_key(pr.file_sha256(pair["fp32"]), pr.file_sha256(pair["int8"]), cf.cpu_features(), 1)
    config.cache_dir.mkdir(parents=True)
    (config.cache_dir / f"precision-{key}.json").write_text(json.dumps(
        {"version": pr.CACHE_VERSION, "fp32_p50_s": 0.0442, "int8_p50_s": 0.0650}))
    choice = pr.pick_model(pair["fp32"], pr.Precision.AUTO, config)
    assert choice.path == pair["fp32"] and choice.precision is pr.Precision.FP32
    assert "INT8 is not faster" in choice.reason and "0.68x" in choice.reason


def test_overrides_and_candidates(pair, tmp_path):
    config = _probe(tmp_path)
    assert pr.pick_model(pair["fp32"], pr.Precision.FP32, config).path == pair["fp32"]
    assert pr.pick_model(pair["fp32"], pr.Precision.INT8, config).path == pair["int8"]
    given = pr.pick_model(pair["int8"], pr.Precision.AUTO, config)
    assert given.path == pair["int8"] and "given as an INT8 file" in given.reason
    with pytest.raises(InputError, match="INT8 model"):
        pr.pick_model(pair["int8"], pr.Precision.FP32, config)
    # the failed twin is never a candidate, and asking for it is an error naming why
    failed = pr.pick_model(pair["bad"], pr.Precision.AUTO, config)
    assert failed.path == pair["bad"] and "failed the accuracy gate" in failed.reason
    with pytest.raises(InputError, match="failed the accuracy gate"):
        pr.pick_model(pair["bad"], pr.Precision.INT8, config)
    assert not config.cache_dir.exists()     # none of these needed a probe


def test_edge_run_flags(pair, tmp_path, capsys):
    (choice,) = choose_files(config_from_args(["--model", str(pair["fp32"]), "--int8"]))
    assert choice.path == pair["int8"]
    # --runtime onnxruntime: this is about the file; OpenVINO may be faster on it (tests/test_runtime_choice.py)
    (choice,) = choose_files(config_from_args(["--model", str(pair["fp32"]), "--precision", "FP32",
                                               "--runtime", "onnxruntime"]))
    assert choice.path == pair["fp32"] and choice.line().startswith("model net.onnx (fp32): asked for")
    assert main(["--model", str(pair["fp32"]), "--precision", "fast"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--precision 'fast'" in err[0] and "auto, fp32, int8" in err[0]


def test_a_copied_twin_of_another_export_is_refused(pair, tmp_path):
    other = tiny_conv_net(tmp_path / "net.onnx", Task.DEPTH_HVO, height=64, width=96, seed=3)
    Path(tmp_path / "net.int8.onnx").write_bytes(pair["int8"].read_bytes())
    choice = pr.pick_model(other, pr.Precision.AUTO, _probe(tmp_path))
    assert choice.path == other and "another FP32 file" in choice.reason
