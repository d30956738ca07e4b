from glob import glob

from setuptools import find_packages, setup

package_name = 'galvoscan'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        # the repository's launch/ folder, for `ros2 launch galvoscan galvoscan.launch.py`
        ('share/' + package_name + '/launch', sorted(glob('../../launch/*'))),
    ],
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='galvoscan developers',
    maintainer_email='galvoscan-dev@example.com',
    description='the galvoscan application: command, bring-up, scan client, evaluation',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'galvoscan = galvoscan.cli:main',
        ],
    },
)
