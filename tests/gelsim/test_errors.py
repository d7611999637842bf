"""gelsim.errors: the one-line error and the shared check of a name against its choices."""
import pytest

from gelsim.errors import GelsimError, check_choice


class OtherError(GelsimError):
    pass


def test_check_choice_names_the_value_and_the_choices():
    check_choice("fidelity", "fast", ("fast", "balanced"))
    with pytest.raises(GelsimError, match=r"^unknown fidelity 'slow'; choose one of fast, balanced$"):
        check_choice("fidelity", "slow", ("fast", "balanced"))
    with pytest.raises(OtherError, match=r"^unknown split 'dev'; choose one of train, val$"):
        check_choice("split", "dev", {"train": 1, "val": 2}, OtherError)
