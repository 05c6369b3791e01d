"""Object detection: the 9-class Faster R-CNN of seed 000 and its backbones (torch; never imported by the runtime)."""
