"""Completion of file names in path fields: typing "r" offers "river.mp4"; → (right) accepts it."""

from __future__ import annotations

from pathlib import Path

from textual.suggester import Suggester

# file kinds each path key expects first (others follow)
PREFERRED = {
    "video.path": (".mp4", ".avi", ".mov", ".mkv", ".mts", ".m4v", ".wmv", ".webm"),
    "cross_section.path": (".csv", ".txt", ".tsv", ".xlsx", ".ods"),
    "calibration.path": (".toml", ".json"),
    "calibration.checkerboard_video": (".mp4", ".avi", ".mov", ".mkv", ".mts"),
    "water_level.dem_path": (".tif", ".tiff"),
    "water_level.image1": (".png", ".jpg", ".jpeg", ".tif"),
    "water_level.image2": (".png", ".jpg", ".jpeg", ".tif"),
}


class PathSuggester(Suggester):
    """Names in the project folder (or the folder typed so far) that start with what is typed;
    the kinds the key expects first, folders with a trailing '/'."""

    def __init__(self, root: Path, key: str) -> None:
        super().__init__(use_cache=False, case_sensitive=True)
        self.root = Path(root)
        self.preferred = PREFERRED.get(key, ())

    async def get_suggestion(self, value: str) -> str | None:
        head, _, prefix = value.rpartition("/")
        folder = Path(head) if head.startswith("/") else self.root / head
        try:
            names = [p for p in folder.iterdir() if p.name.startswith(prefix) and not p.name.startswith(".")]
        except OSError:
            return None
        if not names:
            return None
        names.sort(key=lambda p: (p.suffix.lower() not in self.preferred, not p.is_dir(), p.name.lower()))
        best = names[0]
        name = best.name + ("/" if best.is_dir() else "")
        return value + name[len(prefix) :]
