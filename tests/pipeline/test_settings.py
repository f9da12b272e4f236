"""pipeline.settings: the self-describing setting fields."""

from dataclasses import dataclass

import pytest

from facelab_addon.pipeline.settings import describe, setting


@dataclass
class _S:
    width: float = setting(0.5, label="Width", description="in mm", min=0.0, unit="mm")
    internal: int = 3
    mode: str = setting("a", label="Mode", description="which", choices=(("a", "A", ""), ("b", "B", "")))


def test_describe_lists_only_declared_settings_in_order():
    d = describe(_S)
    assert [x["name"] for x in d] == ["width", "mode"]
    assert d[0]["type"] is float and d[0]["default"] == 0.5 and d[0]["unit"] == "mm" and d[0]["min"] == 0.0
    assert d[1]["choices"][1][0] == "b"
    assert _S().width == 0.5 and _S(width=2.0).width == 2.0


def test_unknown_unit_is_refused():
    with pytest.raises(ValueError, match="unit"):
        setting(1.0, label="X", description="x", unit="inch")
