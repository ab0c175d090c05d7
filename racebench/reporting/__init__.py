"""Reporting: tables, plots, episode videos and the paper's tables, from evaluation results."""
