"""Sans-I/O codecs for busgate's wire protocols: bytes in, typed frames and events out.

One subpackage per protocol (``inspire_la``, ``ds_servo``, ``zlac706_can``,
``zlac706_rs232``). No I/O, no clock, no threads live here.
"""
