"""Object assets built from external model sets (YCB), processed once and cached on disk."""

from bulbjax.assets.cache import CACHE_DIR_ENV, cache_root
from bulbjax.assets.mjcf import ycb_mjcf
from bulbjax.assets.ycb import YCB_DIR_ENV, YCB_INFO, YcbAsset, YcbInfo, load_ycb_object, ycb_dir

__all__ = ["YCB_INFO", "YCB_DIR_ENV", "CACHE_DIR_ENV", "YcbInfo", "YcbAsset", "load_ycb_object",
           "ycb_dir", "ycb_mjcf", "cache_root"]
