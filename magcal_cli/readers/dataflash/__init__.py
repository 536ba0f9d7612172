"""DataFlash logs: ArduPilot binary and text logs and legacy PX4 sdlog2, with ArduPilot's compass correction."""
