"""Optical flow providers: dense (FlowNet 2.0, SpyNet, DIS) and sparse (Shi-Tomasi + Lucas-Kanade), with uncertainty."""
