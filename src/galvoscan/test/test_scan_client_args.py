"""`galvoscan scan` refuses step counts and numbers it cannot send, before contacting anyone."""

import pytest

from galvoscan.scan_client import MAX_STEPS, build_parser


@pytest.mark.parametrize('args, message', [
    (['--steps-pan', '5000000000'], 'outside 1..4294967295'),   # would wrap to 705,032,704
    (['--steps-tilt', '-3'], 'outside 1..'),
    (['--steps-tilt', '0'], 'outside 1..'),
    (['--steps-pan', '2.5'], 'not a whole number'),
    (['--rate', 'nan'], 'not finite'),
    (['--g1-pan', '-1', 'inf'], 'not finite'),
])
def test_bad_arguments_are_refused_by_name(capsys, args, message):
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(args)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert message in err and args[0] in err


def test_limits_are_accepted():
    args = build_parser().parse_args(['--steps-pan', str(MAX_STEPS), '--steps-tilt', '1'])
    assert args.steps_pan == MAX_STEPS and args.steps_tilt == 1


def test_unknown_command_is_named(capsys):
    from galvoscan.cli import main

    assert main(['nosuch']) == 2
    assert "unknown command 'nosuch'" in capsys.readouterr().err
    assert main(['--help']) == 0
    assert 'unknown command' not in capsys.readouterr().err
