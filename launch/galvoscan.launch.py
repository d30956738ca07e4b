"""``ros2 launch`` the galvoscan graph on an apt ROS 2 Jazzy install.

The same nodes, parameters file and process settings as ``galvoscan run`` (one process per
node; ``galvoscan.bringup``)::

    ros2 launch launch/galvoscan.launch.py
    ros2 launch launch/galvoscan.launch.py params_file:=my_params.yaml
    ros2 launch launch/galvoscan.launch.py nodes:=galvo_driver                     # host 1
    ros2 launch launch/galvoscan.launch.py nodes:=stripe_extractor,reconstructor   # host 2

Arguments:
    params_file  parameters YAML laid out ``node_name: ros__parameters: {...}``, the file
                 ``galvoscan run --params`` takes (default: ``galvoscan.params.yaml`` beside
                 this file)
    nodes        comma-separated node names, as ``galvoscan run --nodes`` (default: driver,
                 extractor, reconstructor; ``calibration`` is the fourth)

The parameters file is completed as ``galvoscan run`` completes it
(``galvoscan.bringup.prepare_params``): where it leaves them open, the stripe extractor's
``orientation`` and the driver's ``raster_g1_axis`` follow the rig's calibration (a laser
beside the camera: a stripe along the columns, a raster stepping G1's pan), and with the
simulated rig the calibration node and the reconstructor start from its calibration.

The driver is a lifecycle node; with its ``autostart`` parameter (default true) it
configures and activates itself, so no transition events are needed here. With
``autostart: false`` it waits unconfigured for ``ros2 lifecycle set /galvo_driver
configure`` (then ``activate``). Each node process gets the malloc, BLAS and Fast DDS
settings of ``galvoscan_common.runtime`` (``GALVOSCAN_DDS=multihost`` in the environment
selects the multi-host Fast DDS profile). No namespace argument: the parameters file names
the nodes without one, as ``galvoscan run`` starts them.
"""

import tempfile
from pathlib import Path

from launch.actions import DeclareLaunchArgument, OpaqueFunction, SetLaunchConfiguration
from launch.launch_description import LaunchDescription
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node

from galvoscan.bringup import prepare_params
from galvoscan_common.runtime import ENV, PROFILE_VARS, child_env

#: The parameters file used unless ``params_file:=`` names another (beside this file).
PARAMS_FILE = 'galvoscan.params.yaml'
#: Nodes started unless ``nodes:=`` says otherwise (``galvoscan.bringup.DEFAULT_NODES``).
DEFAULT_NODES = 'galvo_driver,stripe_extractor,reconstructor'


def _runtime_env() -> dict:
    """The process settings ``galvoscan run`` gives its node processes (malloc, BLAS, DDS)."""
    env = child_env()
    return {key: env[key] for key in (*ENV, *PROFILE_VARS) if key in env}


def _nodes(context):
    """The actions of the nodes ``nodes:=`` selects; an unknown name stops the launch."""
    env = _runtime_env()
    actions = {
        'galvo_driver': LifecycleNode(
            package='galvo_driver', executable='galvo_driver', name='galvo_driver',
            namespace='', parameters=[LaunchConfiguration('params_file')],
            additional_env=env, output='screen'),
        'stripe_extractor': Node(
            package='stripe_extractor', executable='stripe_extractor',
            name='stripe_extractor', parameters=[LaunchConfiguration('params_file')],
            additional_env=env, output='screen'),
        'reconstructor': Node(
            package='reconstructor', executable='reconstructor', name='reconstructor',
            parameters=[LaunchConfiguration('params_file')], additional_env=env,
            output='screen'),
        'calibration': Node(
            package='calibration_tools', executable='calibration_node', name='calibration',
            parameters=[LaunchConfiguration('params_file')], additional_env=env,
            output='screen'),
    }
    selected = [n for n in LaunchConfiguration('nodes').perform(context).split(',') if n]
    unknown = [n for n in selected if n not in actions]
    if unknown:
        raise RuntimeError(f"nodes: unknown {', '.join(unknown)}; known: {', '.join(actions)}")
    given = LaunchConfiguration('params_file').perform(context)
    try:
        params = prepare_params(given, selected, tempfile.mkdtemp(prefix='galvoscan-launch-'))
    except ValueError as exc:
        raise RuntimeError(f'params_file: {exc}') from None
    # the nodes read params_file when they are started, after this has set it
    return [SetLaunchConfiguration('params_file', str(params)),
            *(actions[n] for n in selected)]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument(
            'params_file', default_value=str(Path(__file__).with_name(PARAMS_FILE)),
            description='parameters YAML (node_name: ros__parameters: ...), the file '
                        'galvoscan run --params takes'),
        DeclareLaunchArgument(
            'nodes', default_value=DEFAULT_NODES,
            description='comma-separated node names: galvo_driver, stripe_extractor, '
                        'reconstructor, calibration'),
        OpaqueFunction(function=_nodes),
    ])
