"""Simulators of every device family, speaking the real byte protocols on real transports
(a pty for serial, python-can's ``virtual`` bus or an SLCAN adapter on a pty for CAN), with
wire timing and fault injection, so the gateway's tests and demo meet real-hardware timing."""
