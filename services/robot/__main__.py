from services.robot.service import RobotService
from shared.runtime import service_main

service_main("robot", RobotService)
