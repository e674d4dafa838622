"""The host under a real-time run: the CPU latency request and the idle spinners."""
