"""The CPU's instruction-set features that decide INT8 speed (ARCHITECTURE.md §9).

INT8 convolutions pay off only with dot-product instructions: x86 VNNI (AVX512_VNNI, or AVX_VNNI on newer
cores) or AMX, ARM's SDOT/UDOT (``asimddp``) and I8MM. Without them (AVX2 + FMA only) ONNX Runtime's int8
kernels widen to int16 and an INT8 model can be slower than FP32. Read from ``/proc/cpuinfo`` (Linux); on
other systems every flag reads False and ``source`` says so. Example::

    isa = cpu_features()
    print(isa.summary())        # "AMD EPYC 9B14: AVX2 FMA AVX-512F AVX512_VNNI AVX_VNNI"
    isa.int8_dot_product        # True when the CPU has VNNI, AMX-INT8 or ARM dot-product
"""
from __future__ import annotations

import hashlib
import platform
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Dict, Iterable, Tuple

CPUINFO = Path("/proc/cpuinfo")

# label -> the /proc/cpuinfo flag(s), any of which means the feature is there
_FLAGS: Tuple[Tuple[str, Tuple[str, ...]], ...] = (
    ("AVX2", ("avx2",)),
    ("FMA", ("fma",)),
    ("AVX-512F", ("avx512f",)),
    ("AVX512_VNNI", ("avx512_vnni",)),
    ("AVX_VNNI", ("avx_vnni",)),
    ("AVX512_BF16", ("avx512_bf16",)),   # OpenVINO runs float layers in bf16 here unless told f32 (backend.py)
    ("AMX-INT8", ("amx_int8",)),
    ("ARM-DOTPROD", ("asimddp",)),
    ("ARM-I8MM", ("i8mm",)),
)


@dataclass(frozen=True)
class CpuFeatures:
    """The features of the first CPU listed (all cores of the machines this runs on are alike)."""

    model: str
    machine: str                 # platform.machine(): x86_64, aarch64, ...
    features: Tuple[str, ...]    # labels of _FLAGS present, in that order
    source: str                  # "/proc/cpuinfo" or why nothing was read

    def has(self, label: str) -> bool:
        return label in self.features

    @property
    def int8_dot_product(self) -> bool:
        """The CPU multiplies int8 with a dot-product instruction (where INT8 models gain most)."""
        return any(self.has(f) for f in ("AVX512_VNNI", "AVX_VNNI", "AMX-INT8", "ARM-DOTPROD"))

    def summary(self) -> str:
        return f"{self.model}: {' '.join(self.features) or 'no listed SIMD feature'}"

    def key(self) -> str:
        """A short stable hash of model + features, for caches of what was measured on this CPU."""
        return hashlib.sha256(self.summary().encode()).hexdigest()[:12]

    def to_json(self) -> Dict[str, object]:
        d: Dict[str, object] = asdict(self)
        d["features"] = list(self.features)
        d["int8_dot_product"] = self.int8_dot_product
        return d


def parse_cpuinfo(text: str) -> Tuple[str, Tuple[str, ...]]:
    """(model name, feature labels) of the first processor in a /proc/cpuinfo text (x86 ``flags``, ARM
    ``Features``; the model line is ``model name`` on x86 and may be missing on ARM)."""
    model, flags = "", set[str]()
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if not sep:
            continue
        key = key.strip().lower()
        if key in ("model name", "hardware", "cpu model") and not model:
            model = value.strip()
        elif key in ("flags", "features") and not flags:
            flags = set(value.split())
    return model, labels_of(flags)


def labels_of(flags: Iterable[str]) -> Tuple[str, ...]:
    present = set(flags)
    return tuple(label for label, names in _FLAGS if any(n in present for n in names))


@lru_cache(maxsize=1)
def cpu_features() -> CpuFeatures:
    """This machine's features (read once per process)."""
    machine = platform.machine()
    try:
        model, feats = parse_cpuinfo(CPUINFO.read_text())
        source = str(CPUINFO)
    except OSError as exc:
        model, feats, source = "", (), f"{CPUINFO} unreadable ({exc.strerror})"
    return CpuFeatures(model or platform.processor() or machine or "unknown CPU", machine, feats, source)
