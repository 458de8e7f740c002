"""Kept for scripts written against earlier releases, which imported the zenoh session
settings from here: they are ``busgate.schemas.zenoh_session``'s now, the module both the
daemon and the SDK build their sessions with; import them from there."""

from busgate.schemas.zenoh_session import MODES, session_config, session_refusal, zenoh_reason

__all__ = ["MODES", "session_config", "session_refusal", "zenoh_reason"]
