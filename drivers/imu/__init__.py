"""IMUs over I2C (MPU-9250 family with its AK8963, BNO055): the shared sample loop and one module per chip."""
