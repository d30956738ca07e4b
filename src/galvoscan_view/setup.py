from setuptools import find_packages, setup

package_name = 'galvoscan_view'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    include_package_data=True,
    # the browser page; static/vendor holds three.js, put there by `make setup` (npm)
    package_data={package_name: ['static/*.html', 'static/*.js', 'static/*.css', 'static/*.svg',
                                 'static/vendor/*.js', 'static/vendor/*.LICENSE']},
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='galvoscan developers',
    maintainer_email='galvoscan-dev@example.com',
    description='galvoscan view: Foxglove WebSocket bridge and browser page on the graph',
    license='Apache-2.0',
    entry_points={'console_scripts': []},
)
