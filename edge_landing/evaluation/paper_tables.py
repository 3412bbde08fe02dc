"""The paper's published figures (reference/paper.md, Tables 2–7) as data, for side-by-side rows.

Two test sets: ``safeuav`` (in-domain, Tables 2–4) and ``airsimnc`` (zero-shot, Tables 5–7). Missing
values (the paper's '–') are None. Starred depth rows are per-image median-scaled.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

from edge_landing.runtime.core.choices import ChoiceEnum


class PaperDataset(ChoiceEnum):
    SAFEUAV = "safeuav"
    AIRSIMNC = "airsimnc"

    @classmethod
    def _label(cls) -> str:
        return "paper test set"


@dataclass(frozen=True)
class PaperDepthRow:
    model: str
    median_scaled: bool
    a1: float
    a2: float
    a3: float
    abs_rel: float
    rms: float
    log10: Optional[float]


@dataclass(frozen=True)
class PaperSsimRow:
    model: str
    ssim: float
    median_rel: float


@dataclass(frozen=True)
class PaperHvoRow:
    model: str
    cls: str              # horizontal / vertical / other / average / "reported by SafeUAV"
    accuracy: float
    precision: float
    recall: float
    iou: float


def _depth(rows, starred=False):
    return tuple(PaperDepthRow(m, starred, *v) for m, *v in rows)


_T2 = _depth([("AdaBins-80", 0.952, 0.987, 0.992, 0.084, 6.425, 0.033),
              ("AdaBins-256", 0.972, 0.993, 0.996, 0.065, 5.587, 0.026),
              ("DD-UAV", 0.943, 0.998, 1.000, 0.130, 11.118, 0.052),
              ("DD-UAV-NYU", 0.973, 0.996, 0.999, 0.068, 8.451, 0.030)])
_T5_RAW = [("AdaBins-80", 0.388, 0.623, 0.804, 0.608, 42.592, 0.191),
           ("AdaBins-256", 0.249, 0.504, 0.724, 0.930, 51.104, 0.233),
           ("AdaBins-256-KITTI", 0.291, 0.539, 0.725, 0.615, 52.469, 0.218),
           ("AdaBins-256-NYU", 0.166, 0.339, 0.519, 1.409, 70.165, 0.309),
           ("DD-UAV", 0.240, 0.396, 0.507, 0.530, 107.630, 0.383),
           ("DD-UAV-NYU", 0.223, 0.444, 0.647, 0.447, 60.149, 0.249),
           ("DD-KITTI", 0.208, 0.407, 0.585, 1.041, 63.518, None),
           ("DD-NYU", 0.091, 0.190, 0.302, 3.114, 76.365, None)]
_T5_STAR = [("AdaBins-80", 0.588, 0.802, 0.900, 0.338, 33.442, 0.124),
            ("AdaBins-256", 0.567, 0.801, 0.899, 0.393, 33.893, 0.128),
            ("AdaBins-256-KITTI", 0.435, 0.745, 0.848, 0.387, 42.254, 0.156),
            ("AdaBins-256-NYU", 0.415, 0.688, 0.840, 0.380, 46.670, 0.164),
            ("DD-UAV", 0.496, 0.762, 0.891, 0.338, 97.095, 0.135),
            ("DD-UAV-NYU", 0.532, 0.808, 0.920, 0.293, 52.056, 0.123),
            ("DD-KITTI", 0.239, 0.459, 0.649, 0.958, 61.548, None),
            ("DD-NYU", 0.258, 0.492, 0.681, 0.837, 21.257, None)]

_T3 = tuple(PaperSsimRow(*r) for r in [("AdaBins-80", 0.331, 0.004), ("AdaBins-256", 0.318, -0.009),
                                       ("DD-UAV", 0.583, 0.072), ("DD-UAV-NYU", 0.524, 0.036)])
_T6 = tuple(PaperSsimRow(*r) for r in [("AdaBins-80", 0.099, -0.175), ("AdaBins-256", 0.092, -0.564),
                                       ("AdaBins-256-KITTI", 0.178, -0.125), ("AdaBins-256-NYU", 0.057, -1.185),
                                       ("DD-UAV", 0.121, 0.524), ("DD-UAV-NYU", 0.147, 0.205),
                                       ("DD-KITTI", 0.002, -0.044), ("DD-NYU", -0.001, -1.880)])


def _hvo(model, rows):
    return tuple(PaperHvoRow(model, *r) for r in rows)


_T4 = (_hvo("SafeUAV-Net-Large", [("horizontal", 0.827, 0.756, 0.725, 0.587), ("other", 0.725, 0.674, 0.751, 0.551),
                                  ("vertical", 0.852, 0.678, 0.559, 0.442), ("average", 0.801, 0.703, 0.678, 0.527),
                                  ("reported by SafeUAV", 0.846, 0.761, 0.748, 0.607)])
       + _hvo("SafeUAV-Net-Small", [("horizontal", 0.817, 0.703, 0.804, 0.600), ("other", 0.733, 0.715, 0.675, 0.532),
                                    ("vertical", 0.860, 0.689, 0.610, 0.478), ("average", 0.804, 0.702, 0.696, 0.537),
                                    ("reported by SafeUAV", 0.823, 0.728, 0.693, 0.551)]))
_T7 = (_hvo("SafeUAV-Net-Large", [("horizontal", 0.664, 0.724, 0.483, 0.404), ("other", 0.567, 0.252, 0.625, 0.215),
                                  ("vertical", 0.700, 0.467, 0.281, 0.219), ("average", 0.640, 0.481, 0.463, 0.279)])
       + _hvo("SafeUAV-Net-Small", [("horizontal", 0.634, 0.738, 0.366, 0.324), ("other", 0.558, 0.251, 0.629, 0.220),
                                    ("vertical", 0.673, 0.379, 0.273, 0.197), ("average", 0.622, 0.456, 0.423, 0.247)]))


@dataclass(frozen=True)
class PaperTables:
    """One test set's published rows: depth (Table 2 or 5), SSIM/Median Rel (3 or 6), HVO (4 or 7)."""

    dataset: PaperDataset
    depth: Tuple[PaperDepthRow, ...]
    ssim: Tuple[PaperSsimRow, ...]
    hvo: Tuple[PaperHvoRow, ...]
    table_numbers: Tuple[int, int, int]

    def to_json(self) -> dict:
        from dataclasses import asdict

        return {"dataset": self.dataset.value, "tables": list(self.table_numbers), "comparable": False,
                "note": f"the paper's published figures on {self.dataset.value}, another dataset (other images, "
                        f"labels and base rates): for reference only, not comparable with this scene's rows",
                "depth": [asdict(r) for r in self.depth], "ssim": [asdict(r) for r in self.ssim],
                "hvo": [asdict(r) for r in self.hvo]}


PAPER: Dict[PaperDataset, PaperTables] = {
    PaperDataset.SAFEUAV: PaperTables(PaperDataset.SAFEUAV, _T2, _T3, _T4, (2, 3, 4)),
    PaperDataset.AIRSIMNC: PaperTables(PaperDataset.AIRSIMNC, _depth(_T5_RAW) + _depth(_T5_STAR, True), _T6, _T7,
                                       (5, 6, 7)),
}


def paper_tables(dataset: PaperDataset | str = PaperDataset.AIRSIMNC) -> PaperTables:
    if isinstance(dataset, str):
        dataset = PaperDataset.from_string(dataset)
    return PAPER[dataset]
