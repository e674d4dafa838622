"""The run log: MCAP file, recorder, writer process, topics and their schemas, reading logs back."""
