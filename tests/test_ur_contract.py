"""The contract with the pinned ur-rtde: command ids, register layout, recipes, handshake.

The loopback controller plays ur-rtde's control script by its command ids and
registers. If an ur-rtde upgrade renumbers a command or moves an argument, these
tests fail (and the controller refuses the new script) instead of the sim quietly
playing something else.
"""
from __future__ import annotations

import socket
from importlib.metadata import version

import pytest

from drivers.ur import PINNED_UR_RTDE, URRobot
from planning.kinematics import load_robot
from sim_backend.rtde_protocol import PLAYED_COMMANDS, ScriptContractError, check_control_script, command_blocks
from sim_backend.ur_controller import PLAYING, SCRIPT_PORT, STOPPED, LoopbackURController

MODEL = load_robot("ur5e")


def _start_controller(**kwargs) -> LoopbackURController:
    """A controller on a free loopback address in 127.0.9.x (another test run may hold some)."""
    for last in range(2, 250):
        try:
            return LoopbackURController(f"127.0.9.{last}", model=MODEL, **kwargs).start()
        except OSError:
            continue
    raise RuntimeError("no free loopback address for a UR controller")


@pytest.fixture(scope="module")
def uploaded():
    """What the real ur-rtde client uploads and sets up, captured by a loopback controller."""
    with _start_controller(time_scale=4.0) as controller:
        with URRobot(controller.host, model=MODEL) as robot:
            robot.move_joints(controller.joints + 0.05, 0.5, 1.0)
            robot.stop()
        yield {"script": controller.uploaded_scripts[0], "recipes": list(controller.input_recipes),
               "commands": list(controller.commands)}


def _in(kind: str, *idx: int) -> tuple[str, ...]:
    return tuple(f"input_{kind}_register_{i}" for i in idx)


def test_installed_ur_rtde_is_the_pinned_version():
    assert version("ur_rtde") == PINNED_UR_RTDE


def test_uploaded_script_plays_the_command_ids_and_registers_of_the_controller(uploaded):
    script = uploaded["script"]
    assert script.startswith("def rtde_control():\n") and script.rstrip().endswith("end")
    assert check_control_script(script) == 0  # lower register range
    blocks = command_blocks(script)
    for cmd, (name, _) in PLAYED_COMMANDS.items():
        if cmd != 255:
            assert f'textmsg("{name}' in blocks[cmd], f"command {cmd} is no longer {name}"


def test_each_command_travels_in_the_register_layout_the_script_reads(uploaded):
    layout = {c.name: c.recipe for c in uploaded["commands"]}
    # id, 6 joint values, speed (double 6), acceleration (double 7), async flag (int 1)
    assert layout["movej"] == _in("int", 0) + _in("double", *range(8)) + _in("int", 1)
    assert layout["set_watchdog"] == _in("int", 0) + _in("double", 0)  # min frequency in double 0
    assert layout["stopj"] == _in("int", 0) + _in("double", 0) + _in("int", 1)  # deceleration, async
    assert layout["set_tcp"][:7] == _in("int", 0) + _in("double", *range(6))
    assert _in("int", 0) in uploaded["recipes"]  # the clear / kick recipe


def test_the_driver_used_only_commands_the_controller_plays(uploaded):
    played = {c.cmd for c in uploaded["commands"]}
    assert played <= set(PLAYED_COMMANDS)
    assert {"set_tcp", "set_watchdog", "movej", "stopj"} <= {c.name for c in uploaded["commands"]}
    movej = next(c for c in uploaded["commands"] if c.name == "movej")
    assert movej.args["speed"] == 0.5 and movej.args["acceleration"] == 1.0 and movej.args["async"]


@pytest.mark.parametrize("edit, message", [
    (("if cmd == 1:", "if cmd == 101:"), "command 1 \\(movej\\) is missing"),
    (("velocity = read_input_float_reg(6)", "velocity = read_input_float_reg(9)"), "read_input_float_reg\\(6\\)"),
    (("write_output_integer_reg(0, 2)", "write_output_integer_reg(0, 3)"), "signal_done_with_cmd"),
])
def test_a_changed_script_is_refused(uploaded, edit, message):
    changed = uploaded["script"].replace(*edit, 1)
    assert changed != uploaded["script"]
    with pytest.raises(ScriptContractError, match=message):
        check_control_script(changed)


def test_controller_refuses_to_run_a_changed_script_sent_to_port_30003(uploaded):
    changed = uploaded["script"].replace("elif cmd == 3:", "elif cmd == 103:", 1)
    with _start_controller() as controller:
        for text in (changed, uploaded["script"]):
            with socket.create_connection((controller.host, SCRIPT_PORT), timeout=2.0) as conn:
                conn.sendall(text.encode())
            controller.wait_for(lambda n=len(controller.messages): len(controller.messages) > n
                                or controller.runtime_state == PLAYING, 2.0)
            if text is changed:
                assert controller.runtime_state == STOPPED
                assert any("command 3 (movel) is missing" in m for m in controller.messages)
        assert controller.runtime_state == PLAYING  # the genuine script runs
