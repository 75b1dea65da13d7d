"""The position loop's laws and limits: the PD and modal compensators, mode identification, the
controller's limits, the safety gate on poses, and the ledger of increments sent."""
