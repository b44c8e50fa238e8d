"""An Oxford root without traversals: the error names the root and the layout it looked for."""

from pathlib import Path

import pytest

from mining.config import load_config
from mining.errors import InputError
from mining.pipeline.preflight import plan_sequences

JOB = Path(__file__).resolve().parent.parent / "jobs" / "oxford.toml"


def test_no_oxford_sequences_names_root_and_layout(tmp_path: Path) -> None:
    (tmp_path / "not_a_traversal").mkdir()  # a folder without stereo.timestamps
    cfg = load_config(JOB, [f"source.root={str(tmp_path)!r}".replace("'", '"')])
    with pytest.raises(InputError) as e:
        plan_sequences(cfg)
    msg = str(e.value)
    assert str(tmp_path) in msg
    assert "stereo.timestamps" in msg and "GBRG" in msg and "models_dir" in msg and "RobotCar SDK" in msg
