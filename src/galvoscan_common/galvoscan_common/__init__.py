"""Shared by every galvoscan node process: process settings and the executor loop."""
