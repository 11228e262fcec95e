"""The sequence layouts :func:`slam.data.open_sequence` reads: the one table that the config check
(``dataset.layout``), the loader and the command line's help are written from."""

from __future__ import annotations

#: ``dataset.layout`` value that detects the layout from the folder's files.
AUTO = "auto"
#: Layout name -> the dataset format it reads, in the order they are tried.
LAYOUTS: dict[str, str] = {
    "tum": "TUM RGB-D",
    "7scenes": "7-Scenes",
}
#: Every valid ``dataset.layout`` value: ``auto`` and the layouts.
LAYOUT_NAMES: tuple[str, ...] = (AUTO, *LAYOUTS)


def _or_list(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " or " + items[-1]


def layout_names_text() -> str:
    """The valid ``dataset.layout`` values as text: ``auto, tum or 7scenes``."""
    return _or_list(list(LAYOUT_NAMES))


def formats_text() -> str:
    """The dataset formats read as text: ``TUM RGB-D or 7-Scenes``."""
    return _or_list(list(LAYOUTS.values()))
