"""PX4 ULog logs: pyulog behind a guard, and the streams magcal reads from them."""
