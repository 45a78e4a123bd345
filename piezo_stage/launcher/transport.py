"""The middleware's transports a set's participants use (Fast DDS profiles beside this
file), and for the commands and the look that meet a set: light (os alone), so that a
command sets its transport before it imports anything heavy."""

from __future__ import annotations

import os

LOOPBACK_UDP_PROFILE = os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                    "fastdds_loopback_udp.xml")
_OWN_TRANSPORT_KEYS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE",
                       "FASTDDS_BUILTIN_TRANSPORTS", "RMW_FASTRTPS_USE_QOS_FROM_XML")


def realtime_transport_env(env) -> dict[str, str]:
    """The environment that keeps a real-time set's participants off Fast DDS's
    shared-memory transport, on the discovery range ``env`` asks for.

    A participant that first sends to a joining participant's shared-memory port runs
    the port's health check, which can wait ~333 ms on a healthy idle port while it holds
    the participant's send lock (Fast-DDS issue 6535); every publisher of that node waits
    too, and the driver faulted on stale commands when anyone started a node. UDP has no
    such check. LOCALHOST: rmw_fastrtps would add shared memory back, so the range goes
    to SUBNET with a profile that is LOCALHOST's discovery on UDP over 127.0.0.1 alone
    (fastdds_loopback_udp.xml). SUBNET or unset: the built-in UDPv4 transport alone.
    Left as it is: another RMW, discovery OFF, or a transport configuration of the
    user's own (a profiles file, FASTDDS_BUILTIN_TRANSPORTS, QoS from XML).
    """
    if env.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp" or any(
            env.get(k) for k in _OWN_TRANSPORT_KEYS):
        return {}
    scope = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "")
    if not scope and env.get("ROS_LOCALHOST_ONLY") == "1":
        scope = "LOCALHOST"
    if scope == "LOCALHOST":
        return {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
                "FASTRTPS_DEFAULT_PROFILES_FILE": LOOPBACK_UDP_PROFILE}
    if scope in ("", "SUBNET", "SYSTEM_DEFAULT"):
        return {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}
    return {}


LOCKSTEP_PROFILE = os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                "fastdds_lockstep.xml")


def lockstep_transport_env(env) -> dict[str, str]:
    """The environment of a lockstep set's nodes: writers' heartbeats every 50 ms
    (fastdds_lockstep.xml), so the driver's last wait for its readers' acknowledgements
    takes milliseconds, not up to Fast DDS's 3 s period. Left as it is: another RMW, or
    a Fast DDS configuration of the user's own."""
    if env.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp" or any(
            env.get(k) for k in _OWN_TRANSPORT_KEYS):
        return {}
    return {"FASTRTPS_DEFAULT_PROFILES_FILE": LOCKSTEP_PROFILE}
