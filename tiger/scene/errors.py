"""The one exception every scene/camera/dataset reader raises for bad input."""
from __future__ import annotations

import os
from typing import Optional, Union


class SceneFormatError(ValueError):
    """A scene, camera or dataset file is missing, truncated or malformed.

    The message always names the file and, where one is involved, the field
    (PLY property, COLMAP record, JSON key) that is wrong.
    """

    def __init__(self, path: Union[str, os.PathLike, None], message: str,
                 field: Optional[str] = None) -> None:
        self.path = None if path is None else str(path)
        self.field = field
        where = f"{self.path}: " if self.path else ""
        what = f"field '{field}': " if field else ""
        super().__init__(f"{where}{what}{message}")
