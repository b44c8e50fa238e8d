"""Fitted weights as package data: ``mining/score/fits/*.toml``, each fit with its provenance.

Weights fit on synthetic truth are the output of a bench run, not literals in the code. Each
lives in a TOML file of this package, written by the bench that fit it and read here when the
score settings load (``mining.score.config``: ``CALIBRATED``, ``OBJECT_EVIDENCE``,
``ROW_ON_OBJECT``, ``ROW_KNOWN``, the defaults a job config may change):

* ``<proposer>.toml``: the fits for that proposer's evidence, one table each:
  ``[unary]`` the calibrated unary (``mining.score.calibrated``; ``mine bench calibrate
  --write``) and ``[object_evidence]`` the object evidence of a tube called unknown
  (``mining.score.clutter``; ``mine bench calibrate --calling --write``), its weights in
  ``[<fit>.weights]``;
* ``rows.toml``: ``[rows]``, the calibrated confidence of a classifier's own rows
  (``mining.score.category.RowConfidence``; ``mine bench calibrate --calling --write``), its
  two logistics in ``[rows.on_object]`` and ``[rows.known]``.

Every fit table carries its provenance beside the weights: ``command`` (what was run),
``commit`` (the code it ran on; for the fits made before issue 38, the commit that recorded
them), ``proposer``, ``seeds`` and ``frames`` (the synthetic training seeds, frames each),
``samples`` (the counts it was fit on), ``auc`` (leave-one-seed-out ROC AUC on the held-out
seeds) and a ``note``. A bench's ``--write`` replaces its own table and keeps the others.
Written with tomli-w, which spells a float as Python's ``repr``: it reads back as the same float.
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Mapping
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any

import tomli_w

from mining.errors import decode_text
from mining.files import read_text

FITS_DIR = Path(__file__).resolve().parent / "fits"  # where `--write` writes by default (the package's own files)
ROWS = "rows"  # rows.toml: the classifier rows' confidence; every other file is a proposer's
UNARY_FIT, OBJECT_FIT = "unary", "object_evidence"  # the fit tables of a proposer's file
HEADERS = {
    ROWS: ("The calibrated confidence of a classifier's own rows (mining/score/fits.py), written by",
           "`mine bench calibrate --calling --write`; the table records how it was made."),
    "proposer": ("The fitted weights for proposer {name!r} (mining/score/fits.py): [unary] written by",
                 "`mine bench calibrate --write`, [object_evidence] by `mine bench calibrate --calling --write`;",
                 "each table records how it was made."),
}


def _folder(folder: Path | str | None) -> Traversable:
    return resources.files("mining.score").joinpath("fits") if folder is None else Path(folder)


def read_fits(folder: Path | str | None = None) -> dict[str, dict[str, Any]]:
    """Every fit file, by its name without ``.toml`` (``folder``: another than the package's)."""
    out = {}
    for entry in sorted(_folder(folder).iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            try:
                out[entry.name[: -len(".toml")]] = tomllib.loads(decode_text(entry.read_bytes(), str(entry), "fit file"))
            except tomllib.TOMLDecodeError as e:
                raise ValueError(f"fit file {entry.name}: not valid TOML: {e}") from None
    return out


def _floats(table: Mapping[str, Any], where: str) -> dict[str, float]:
    if not isinstance(table, Mapping) or not all(isinstance(v, float) for v in table.values()):
        raise ValueError(f"fit file {where}: expected a table of numbers")
    return dict(table)


def proposer_weights(fit: str, folder: Path | str | None = None) -> dict[str, dict[str, float]]:
    """Proposer → the weights of its ``fit`` table (``UNARY_FIT`` or ``OBJECT_FIT``), for the
    proposers whose file has one."""
    return {name: _floats(doc[fit]["weights"], f"{name}.toml [{fit}.weights]")
            for name, doc in read_fits(folder).items() if name != ROWS and fit in doc}


def row_weights(folder: Path | str | None = None) -> tuple[dict[str, float], dict[str, float]]:
    """(on_object, known): the two logistics of the classifier rows' confidence."""
    rows = read_fits(folder)[ROWS][ROWS]
    return _floats(rows["on_object"], "rows.toml [rows.on_object]"), _floats(rows["known"], "rows.toml [rows.known]")


def _finite(v: Any) -> None:
    """A fit holds finite numbers only (TOML could spell nan and inf; no weight should be one)."""
    if isinstance(v, float) and not math.isfinite(v):
        raise ValueError(f"a fit holds finite numbers only, got {v!r}")
    for x in v.values() if isinstance(v, Mapping) else v if isinstance(v, (list, tuple)) else ():
        _finite(x)


def fit_text(name: str, doc: Mapping[str, Mapping[str, Any]]) -> str:
    """The text of fit file ``name`` (``ROWS`` or a proposer) holding the fit tables ``doc``."""
    _finite(doc)
    header = HEADERS[ROWS] if name == ROWS else tuple(line.format(name=name) for line in HEADERS["proposer"])
    return "".join(f"# {line}\n" for line in header) + "\n" + tomli_w.dumps(doc)  # floats as their repr


def updated_fit(name: str, fit: str, table: Mapping[str, Any],
                folder: Path | str | None = None) -> tuple[Path, str]:
    """``<folder>/<name>.toml`` and its new text: the fit table ``fit`` (provenance and weights)
    replaced by ``table``, the file's other tables kept (``folder``: the package's own,
    ``FITS_DIR``, by default). The caller writes it (``mine bench calibrate --write``)."""
    path = Path(folder or FITS_DIR) / f"{name}.toml"
    doc = tomllib.loads(read_text(path, "fit file")) if path.is_file() else {}
    doc[fit] = json.loads(json.dumps(table))  # plain lists and tables, as TOML reads them back
    text = fit_text(name, doc)
    if tomllib.loads(text) != doc:  # what is written must read back as given
        raise ValueError(f"fit {name} [{fit}] does not survive a round trip through TOML")
    return path, text
