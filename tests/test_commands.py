"""Issue 44: one module per command of the command line, each with one shape (a Command: its
config, ``run(cfg, progress)``), registered once; the CLI loops over the registry and each job's
config is checked once. No JAX compile: the jobs are stopped right after their check."""

import ast
import dataclasses
import inspect
import pathlib

import pytest

from wbc_jax import cli, commands
from wbc_jax.commands import Command, registry
from wbc_jax.jobs import balance, envelope, limit, sweep_config
from wbc_jax.robot import model

COMMANDS_DIR = pathlib.Path(commands.__file__).parent


def test_the_registry_is_the_command_line():
    """Every CLI command is in the registry and every registry entry is a CLI command; one module per
    command, named after it, and no command module left out of the registry."""
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert list(sub.choices) == list(registry())
    modules = sorted(p.stem for p in COMMANDS_DIR.glob("*.py") if p.stem != "__init__")
    assert modules == sorted(commands.MODULES) == sorted(n.replace("-", "_") for n in registry())


@pytest.mark.parametrize("name", list(commands.MODULES))
def test_every_command_has_the_one_shape(name):
    import importlib

    module = importlib.import_module(f"wbc_jax.commands.{name}")
    command = module.COMMAND
    assert isinstance(command, Command) and command.name.replace("-", "_") == name
    assert registry()[command.name] is command
    assert list(inspect.signature(command.run).parameters) == ["cfg", "progress"]
    config = command.default_config()
    assert dataclasses.is_dataclass(config) and callable(config.check)
    for shared, skip in command.shared:
        assert set(skip) <= {f.name for f in dataclasses.fields(shared())}
    assert (command.combine is None) == (not command.shared)


def test_the_cli_names_no_command():
    """The command line loops over the registry: no command's name appears in cli.py."""
    tree = ast.parse(pathlib.Path(cli.__file__).read_text())
    names = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    assert not names & set(registry()), sorted(names & set(registry()))


# command -> (its config class, what to stop right after the check: (module, attribute))
STOPS = {
    "balance": (balance.BalanceConfig, (balance, "make_setup")),
    "push-sweep": (sweep_config.SweepConfig, (model, "load_robot")),
    "envelope": (envelope.EnvelopeConfig, (model, "load_robot")),
    "limit": (limit.LimitConfig, (model, "load_robot")),
}


@pytest.mark.parametrize("name", sorted(STOPS))
def test_each_job_checks_its_config_once(name, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    config_class, (module, attribute) = STOPS[name]
    calls = []
    check = config_class.check

    def counted(self):
        calls.append(type(self).__name__)
        return check(self)

    def stop(*args, **kwargs):
        raise ValueError("stopped after the check")

    monkeypatch.setattr(config_class, "check", counted)
    monkeypatch.setattr(module, attribute, stop)
    assert cli.main([name, "--quiet", "--out", str(tmp_path / "out")]) == 2
    assert "stopped after the check" in capsys.readouterr().err
    assert calls == [config_class.__name__], calls


CONTROLLER_FLAGS = (
    "tasks",
    "forces",
    "postural",
    "angular_weight_soft",
    "qp_warm_start",
    "qp_unrolled_steps",
    "qp_engine",
)


def _configs():
    """Every config a command takes (its own and the shared ones), by command."""
    for name, command in registry().items():
        yield name, [command.default_config(), *(shared() for shared, _ in command.shared)]


def test_every_job_takes_the_robot_and_the_controller_flags_from_one_declaration():
    """Issue 44/47: ``--robot`` is one field declared once (wbc_jax/robot/robots.py) in every job's
    config but view's (a run's robot is in its folder), and the controller's flags are one nested
    :class:`ControllerFlags`, never declared by a job's own config."""
    from wbc_jax.control.flags import ControllerFlags
    from wbc_jax.core import options
    from wbc_jax.robot.robots import ROBOT_NAMES

    declared = {f.name: f for f in dataclasses.fields(ControllerFlags)}
    for name, configs in _configs():
        for config in configs:
            own = {f.name: f for f in dataclasses.fields(config)}
            assert not set(CONTROLLER_FLAGS) & set(own), (name, type(config).__name__)
            for field in options.flat_fields(config):
                if field.name in CONTROLLER_FLAGS:
                    assert field is declared[field.name], (name, field.name)
        if name != "view":
            robot = {f.name: f for f in dataclasses.fields(configs[0])}["robot"]
            assert robot.metadata["valid"].choices == ROBOT_NAMES, name
    assert set(ROBOT_NAMES) >= {"icub", "talos"}


@pytest.mark.parametrize("flags, warm", [([], False), (["--qp-warm-start"], True), (["--no-qp-warm-start"], False)])
def test_qp_warm_start_flag_reaches_the_controller(flags, warm):
    """Issue 46: ``--qp-warm-start`` (off by default) is the controller's ``qp_warm_start`` in every job."""
    from wbc_jax import cli

    for command in ("push-sweep", "balance"):
        config = cli.config_from_args(
            cli.build_parser().parse_args([command, *flags]), registry()[command].default_config()
        )
        assert config.controller.config().qp_warm_start is warm, (command, flags)


def test_qp_unrolled_steps_flag_reaches_the_controller_and_refuses_what_the_qp_cannot_take():
    """Issue 46: ``--qp-unrolled-steps`` (0 by default) is the controller's ``qp_unrolled_steps``; a count beyond
    the QP's iterations is one line naming the range."""
    from wbc_jax import cli
    from wbc_jax.control.controller import ControllerConfig

    for command in ("push-sweep", "balance"):
        for flags, steps in (([], 0), (["--qp-unrolled-steps", "6"], 6)):
            config = cli.config_from_args(
                cli.build_parser().parse_args([command, *flags]), registry()[command].default_config()
            )
            assert config.controller.config().qp_unrolled_steps == steps, (command, flags)
    with pytest.raises(ValueError, match=r"qp_unrolled_steps must be an integer from 0 to qp_iterations \(5\)"):
        ControllerConfig(qp_iterations=5, qp_unrolled_steps=6)


def test_qp_engine_flag_reaches_the_controller_and_refuses_what_the_qp_cannot_take(capsys):
    """Issue 46 (s58): ``--qp-engine`` (auto by default, resolved when the job's config is made: s62) is the
    controller's ``qp_engine``; an unknown engine is refused by the parser, and warp with unrolled steps (the Warp
    kernel has no while loop) by the controller."""
    from wbc_jax import cli
    from wbc_jax.control import qp
    from wbc_jax.control.controller import ControllerConfig

    for command in ("push-sweep", "balance"):
        for flags, engine in (([], qp.resolve_engine("auto")), (["--qp-engine", "warp"], "warp")):
            config = cli.config_from_args(
                cli.build_parser().parse_args([command, *flags]), registry()[command].default_config()
            )
            assert config.controller.config().qp_engine == engine, (command, flags)
        with pytest.raises(SystemExit):
            cli.build_parser().parse_args([command, "--qp-engine", "cuda"])
        assert "--qp-engine" in capsys.readouterr().err
    with pytest.raises(ValueError, match=r"qp_engine 'warp' takes qp_unrolled_steps 0"):
        ControllerConfig(qp_engine="warp", qp_unrolled_steps=6)


def test_the_robot_is_part_of_every_fingerprint(tmp_path):
    """The same job on two robots is two runs: the fingerprint holds the robot and its model file."""
    from wbc_jax.core import options

    for cls in (balance.BalanceConfig, sweep_config.SweepConfig, limit.LimitConfig):
        fingerprint = limit.fingerprint if cls is limit.LimitConfig else cls.fingerprint
        icub, talos = (fingerprint(options.replace(cls(), robot=r, out=str(tmp_path / r))) for r in ("icub", "talos"))
        assert (icub["config"]["robot"], talos["config"]["robot"]) == ("icub", "talos"), cls
        assert icub["model"] != talos["model"], cls


def test_an_unknown_robot_is_one_line(capsys):
    with pytest.raises(SystemExit):
        cli.main(["balance", "--robot", "atlas"])
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--robot" in err and "'atlas'" in err and "talos" in err, err
