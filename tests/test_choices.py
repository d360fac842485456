"""String choices (residual, robust kernel, LM model and linear solver) are enums checked once where a
config or LMParams is built; they keep their strings in YAML, JSON and text."""

import json

import pytest
import yaml

from dran_edge.config import AgentConfig, Residual, RobustKernel, config_to_dict
from dran_edge.errors import ConfigError
from dran_edge.solver.lm import Hessian, LinearSolver, LMParams, NewtonDamping


def test_agent_config_strings_become_members():
    cfg = AgentConfig(residual="chordal", robust_kernel="cauchy")
    assert cfg.residual is Residual.CHORDAL
    assert cfg.robust_kernel is RobustKernel.CAUCHY
    assert cfg.residual == "chordal"  # still the string it was


def test_agent_config_bad_choice_names_field_value_and_allowed():
    with pytest.raises(ConfigError) as info:
        AgentConfig(robust_kernel="tukey")
    msg = str(info.value)
    assert msg.startswith("robust_kernel:")
    assert "'tukey'" in msg
    for allowed in ("'none'", "'huber'", "'cauchy'"):
        assert allowed in msg


def test_members_serialise_as_their_strings():
    cfg = AgentConfig(residual="chordal")
    plain = config_to_dict(cfg)
    assert type(plain["residual"]) is str and plain["residual"] == "chordal"
    assert "residual: chordal" in yaml.safe_dump(plain)
    assert json.dumps({"r": cfg.residual}) == '{"r": "chordal"}'
    assert f"{cfg.residual}" == str(cfg.residual) == "chordal"


def test_lm_params_choices():
    params = LMParams(hessian="exact", linear_solver="auto", newton_damping="shared")
    assert params.hessian is Hessian.EXACT
    assert params.linear_solver is LinearSolver.AUTO
    assert params.newton_damping is NewtonDamping.SHARED
    assert LMParams().linear_solver is LinearSolver.SUPERLU
    with pytest.raises(
        ValueError,
        match=r"linear_solver: expected one of 'superlu', 'cholesky', "
        r"'auto', got 'lu'",
    ):
        LMParams(linear_solver="lu")
    with pytest.raises(ValueError, match="hessian: .*'newton'"):
        LMParams(hessian="newton")
