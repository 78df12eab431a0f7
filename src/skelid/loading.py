"""One entry for a model file: a skelid TOML description or an OpenSim ``.osim`` model.

:func:`load_model` picks the reader by the file's suffix, and for a file with
another suffix by its first character (an ``.osim`` file is XML, so it opens
with ``<``): :func:`skelid.model.load_model` for TOML,
:func:`skelid.io.osim.load_osim` for OpenSim (its MarkerSet found beside it
when the model carries no markers, one log-normal scale factor per body that
carries markers, as ``skelid fit`` starts from). Every problem is one
:class:`~skelid.errors.ModelError` or :class:`~skelid.errors.FormatError`
line naming the file.
"""

from __future__ import annotations

from pathlib import Path

from skelid.errors import ModelError
from skelid.model.description import Model
from skelid.model.description import load_model as load_toml


def load_model(path, marker_set=None, scale: str = "bodies", markers: str = "none", marker_names=None) -> Model:
    """Read a model from a TOML file or an OpenSim ``.osim`` file.

    Parameters
    ----------
    path : str or Path
    marker_set : str or Path, optional
        OpenSim only: a MarkerSet ``.xml`` file for a model without markers.
    scale : {'bodies', 'axes', 'none'}
        OpenSim only: one scale factor per body that carries markers, three per body, or none.
    markers : {'offsets', 'none'}
        OpenSim only: an offset of every free marker as a parameter too, or none (the default: a live
        session with three parameters per marker is slow to settle).
    marker_names : iterable of str, optional
        OpenSim only: the markers the data carry; the model keeps only those (and the bodies that lead to
        them), as ``skelid fit`` does, so that a marker the data never have is not reported missing.

    Returns
    -------
    Model

    Raises
    ------
    ModelError, FormatError
        One line naming the file, the problem and the fix.
    """
    from skelid.io._common import check_regular_file

    path = check_regular_file(path, "model file", ModelError)
    if _is_osim(path):
        from skelid.io.osim import load_osim

        return load_osim(path, marker_set, scale=scale, markers=markers, marker_names=marker_names)
    if marker_set is not None:
        raise ModelError(f"{path}: a marker set is for an OpenSim .osim model, not a TOML one",
                         "list the markers in the TOML file, or leave the marker set out")
    return load_toml(path)


def _is_osim(path: Path) -> bool:
    if path.suffix.lower() == ".osim":
        return True
    if path.suffix.lower() == ".toml":
        return False
    try:
        with open(path, "rb") as fh:
            head = fh.read(64).lstrip(b"\xef\xbb\xbf \t\r\n")
    except OSError:
        return False  # the TOML reader says why in one line
    return head.startswith(b"<")
