"""Offline perception tooling: labelled sets, training and evaluation of the 2-D keypoint detector
(``xm detector``). The network and the runtime detector recon uses live in
services/recon/learned_detector.py."""
