from glob import glob

from setuptools import find_packages, setup

package_name = 'lie_dynamics'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'bench', 'bench.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*')),
        ('share/' + package_name + '/launch', glob('launch/*.py')),
    ],
    package_data={package_name: ['data/*.urdf', 'codegen/*.c']},
    install_requires=['setuptools', 'numpy', 'yourdfpy', 'scipy', 'rosbags', 'PyYAML'],
    zip_safe=True,
    maintainer='lie_dynamics developers',
    maintainer_email='lie-dynamics@example.org',
    description='Lie-group rigid-body dynamics (Park, Bobrow & Ploen 1995) and a ROS 2 dynamics node',
    license='BSD-3-Clause',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'dynamics_node = lie_dynamics.ros.node:main',
            'sim_node = lie_dynamics.sim.sim_node:main',
            'trajectory_source = lie_dynamics.sim.trajectory_source:main',
            'demo = lie_dynamics.sim.demo:main',
            'fill_trajectory = lie_dynamics.trajectory:main',
            'excitation_trajectory = lie_dynamics.calibration.excitation:main',
            'identify_dynamics = lie_dynamics.calibration.identify:main',
        ],
    },
)
