"""Empty: LeRobot imports the module; augmentation is not used by the tests."""

v2 = None
