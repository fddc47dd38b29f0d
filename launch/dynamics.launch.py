"""Start the dynamics node with a parameter file (needs a full ROS 2 install: launch, launch_ros).

    ros2 launch lie_dynamics dynamics.launch.py params_file:=/path/to/params.yaml
    ros2 launch lie_dynamics dynamics.launch.py \
        params_file:=$(ros2 pkg prefix lie_dynamics)/share/lie_dynamics/config/arm7_feedforward.yaml
    ros2 launch lie_dynamics dynamics.launch.py namespace:=robot1   # one robot of several

Every topic of the node is relative or private, so with namespace:=robot1 it reads
/robot1/joint_states and /robot1/robot_description and commands /robot1/effort_controller/commands
(only /diagnostics stays global). The shipped parameter files use `/**:`, which matches the node in
any namespace. The filled trajectories (~/trajectory_out) are remapped to joint_trajectory_controller's
input in the same namespace; change it with trajectory_out:=<controller_name>/joint_trajectory.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    default_params = PathJoinSubstitution([FindPackageShare('lie_dynamics'), 'config', 'arm7_gravity.yaml'])
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='Parameter file of the dynamics node'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='Namespace of the node and all its topics (empty: none)'),
        DeclareLaunchArgument('trajectory_out', default_value='joint_trajectory_controller/joint_trajectory',
                              description='Where trajectories with filled efforts go (relative: in the namespace)'),
        Node(package='lie_dynamics', executable='dynamics_node', name='dynamics_node', output='screen',
             namespace=LaunchConfiguration('namespace'),
             parameters=[LaunchConfiguration('params_file')],
             remappings=[('~/trajectory_out', LaunchConfiguration('trajectory_out'))]),
    ])
