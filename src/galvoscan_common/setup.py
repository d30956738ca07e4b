from setuptools import find_packages, setup

package_name = 'galvoscan_common'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    package_data={package_name: ['fastdds_profile.xml', 'fastdds_multihost.xml']},
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='galvoscan developers',
    maintainer_email='galvoscan-dev@example.com',
    description='galvoscan process settings and the executor loop shared by every node',
    license='Apache-2.0',
    entry_points={'console_scripts': []},
)
