"""The one exception every scene/camera/dataset reader raises for bad input."""
from __future__ import annotations

import os
from typing import Optional, Sequence, Union


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


class MissingImagesError(SceneFormatError):
    """Views of a dataset whose image files are missing: names them all (the first ten shown).

    ``missing`` lists every missing file as the dataset names it (relative to ``path``),
    ``total`` counts the views. The message ends with
    ``hint`` (how to skip them); a command-line front end replaces it with its flag through
    :meth:`with_hint`.
    """

    SHOWN = 10

    def __init__(self, path: Union[str, os.PathLike, None], missing: Sequence[str], total: int,
                 field: Optional[str] = None, hint: str = "pass skip_missing=True to skip them") -> None:
        self.missing, self.total, self.hint = [str(m) for m in missing], int(total), hint
        shown = ", ".join(self.missing[:self.SHOWN])
        more = f" and {len(self.missing) - self.SHOWN} more" if len(self.missing) > self.SHOWN else ""
        super().__init__(path, f"{len(self.missing)} of {self.total} images not found: {shown}{more}; {hint}",
                         field)

    def with_hint(self, hint: str) -> "MissingImagesError":
        """The same error with another way of skipping the views named at the end."""
        return MissingImagesError(self.path, self.missing, self.total, self.field, hint)
