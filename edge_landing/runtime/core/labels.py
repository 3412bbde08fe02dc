"""The HVO label set shared by the model contract, the scene folders and fusion (ARCHITECTURE.md §4, §5)."""
from __future__ import annotations

HVO_CLASSES = ("horizontal", "vertical", "other")
HVO_IGNORE = 255
