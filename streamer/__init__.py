"""The runtime: FIFO feeders, the multi-axis coordinator, the job service, the Zenoh API, client and CLI."""
