"""restored_environ puts set, changed and unset variables back, also when the block raises."""
import os

import pytest

from mmflow.environ import restored_environ


def test_variables_are_put_back_set_and_unset(monkeypatch):
    monkeypatch.setenv("MMFLOW_T_SET", "a")
    monkeypatch.delenv("MMFLOW_T_UNSET", raising=False)
    with pytest.raises(RuntimeError):
        with restored_environ("MMFLOW_T_SET", "MMFLOW_T_UNSET"):
            os.environ.update(MMFLOW_T_SET="b", MMFLOW_T_UNSET="c")
            raise RuntimeError
    assert os.environ["MMFLOW_T_SET"] == "a" and "MMFLOW_T_UNSET" not in os.environ
