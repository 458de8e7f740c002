"""ROS 2's wire format as rmw_zenoh speaks it, without ROS: pure, no I/O, no zenoh.

``cdr`` holds the CDR writer and reader, ``definitions`` the ``.msg``/``.srv`` text of each
type busgate speaks, ``messages`` encoding and decoding by type name, ``type_hash`` REP 2016
hashes computed from the definitions, ``rmw_zenoh`` the keys, liveliness tokens, QoS text,
attachment and ROS name rules.
"""
