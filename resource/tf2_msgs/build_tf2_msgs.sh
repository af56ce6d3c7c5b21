#!/usr/bin/env bash
echo "tf2_msgs build: not written yet" >&2; exit 1
