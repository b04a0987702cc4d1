"""Off-screen volume rendering and keyframe animation (VTK, imageio-ffmpeg)."""
