"""dc_sim: a small simulated differential-drive robot in a warehouse, for demonstrating and testing DC.

Gazebo and Nav2 cannot be installed next to DC's pip-installed ROS 2, so this package stands in for
them: it publishes what a real robot's stack does (``/odom``, ``/tf``, ``/tf_static``, ``/map``,
``/cmd_vel`` and optionally ``/clock``) while following a scripted route, and can write its ground
truth to a file so that DC's robot measurements can be checked against it.

The kinematics and the warehouse are pure Python (:mod:`dc_sim.kinematics`, :mod:`dc_sim.warehouse`);
only :mod:`dc_sim.node` needs rclpy.
"""
