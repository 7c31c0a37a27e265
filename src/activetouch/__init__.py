"""activetouch: active tactile and visuo-tactile pose estimation of known objects."""

__version__ = "0.1.0"
