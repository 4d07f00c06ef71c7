"""VDA 5050 (version 2.0) over MQTT: the robot as an AGV of a fleet's master control (docs/fleet.md).

- ``schemas/``: the official VDA 5050 2.0.0 JSON schemas, unmodified, with their licence;
- ``validation``: incoming and outgoing messages checked against them (jsonschema);
- ``orders``: an ``order`` message read strictly into nodes, edges and the path to drive;
- ``agv``: the AGV's side of the protocol (orders and updates, instant actions, state), on an
  explicit vehicle interface, so that it runs on the real-time app and on the simulated clock;
- ``link``: the MQTT client (paho's own thread) and the app service that ties them together.

Needs the ``fleet`` extra (paho-mqtt, jsonschema); nothing here is imported unless the robot
config enables the fleet link.
"""
