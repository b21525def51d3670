"""Camera hub: frames triggered together at a set rate, JPEG CompressedImage + CameraInfo per camera."""
