"""The built-in demo: a simulated robot (swanky_bot, a TurtleBot3-burger-sized differential drive)
driving laps through a walled apartment, seen through the real relay -> Zenoh -> host path.

It gives the bridge, its tests and its demos a robot without ROS, Gazebo or a recorded bag: the
messages are real CDR from the ROS 2 Humble definitions, with the frames, rates and QoS a real
robot offers, and everything is a pure function of time and start position, so two runs give
the same bytes.

- :mod:`~host_bridge.demo.world`: the apartment's walls and exact ray casting against them.
- :mod:`~host_bridge.demo.robot`: the robot's URDF, frames, motion along the loop and its
  drifting wheel odometry (the robot runs no SLAM and publishes no map).
- :mod:`~host_bridge.demo.sensors`: lidar, RGB-D camera, IMU and battery readings.
- :mod:`~host_bridge.demo.driver`: what the robot keeps from tick to tick, and its log lines.
- :mod:`~host_bridge.demo.messages`: the topics as CDR messages (the ground truth too),
  :func:`simulate` a whole run.
- :mod:`~host_bridge.demo.bag`: the run written as a rosbag2.
- :mod:`~host_bridge.demo.run`: ``swanky-host --demo``, one relay per simulated robot.

Nothing is imported here, so the simulation's modules load without Zenoh and the relay.
"""
