"""Empty: imported by LeRobot's processors for image steps the tests do not use."""
