"""``argus robot-agent``: one robot on Zenoh.

Publishes the robot camera's frames with the odometry pose, its state and its navigable viewpoints,
and drives to the next-best-view goals it receives through a body backend (the simulated body now;
a real base such as a ROS 2 bridge is another backend behind the same Protocol). Importing this
package has no side effects and pulls in neither torch nor the simulator.
"""
