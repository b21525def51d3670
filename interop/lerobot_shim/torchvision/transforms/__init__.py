"""Empty: LeRobot imports the module; image augmentation is not used by the tests."""
