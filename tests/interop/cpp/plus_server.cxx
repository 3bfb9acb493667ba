// PLUS stand-in: an OpenIGTLink server (C++ library) that streams the probe pose at 100 Hz.
//   plus_server PORT SECONDS INVALID_AT RECONNECT_AT
// From each accepted connection: the pose rests 2 s on the phantom's top, then pushes 0-6 mm
// (2 s period). Once, a TRANSFORM named "Tracker" (the stock example's name). For 1 s from
// INVALID_AT, an identity TRANSFORM with metadata TransformStatus=INVALID, as PLUS sends an
// occluded tool with SendValidTransformsOnly=FALSE. At RECONNECT_AT the connection is closed
// and the next one accepted (a tracker restart). Ends after SECONDS.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <thread>

#include "igtlServerSocket.h"
#include "igtlTransformMessage.h"
#include "igtl_transform.h"
#include "raw_v2.h"

static double now_s() {
  using namespace std::chrono;
  return duration<double>(steady_clock::now().time_since_epoch()).count();
}

static int send_pose(igtl::Socket* sock, const char* device, double z) {
  igtl::TransformMessage::Pointer msg = igtl::TransformMessage::New();
  msg->SetDeviceName(device);
  igtl::Matrix4x4 m = {{1, 0, 0, 0}, {0, -1, 0, 0}, {0, 0, -1, (float)z}, {0, 0, 0, 1}};
  msg->SetMatrix(m);
  msg->Pack();
  return sock->Send(msg->GetPackPointer(), msg->GetPackSize());
}

static int send_invalid(igtl::Socket* sock) {
  igtl_float32 t[12] = {1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0};  // identity, column-major
  igtl_transform_convert_byte_order(t);
  Bytes content((unsigned char*)t, (unsigned char*)t + sizeof(t));
  std::vector<std::pair<std::string, std::string> > meta;
  meta.push_back(std::make_pair(std::string("TransformStatus"), std::string("INVALID")));
  Bytes msg = pack_v2("TRANSFORM", "ProbeToReference", content, meta);
  return sock->Send(msg.data(), (int)msg.size());
}

int main(int argc, char** argv) {
  if (argc != 5) {
    std::fprintf(stderr, "usage: plus_server PORT SECONDS INVALID_AT RECONNECT_AT\n");
    return 2;
  }
  int port = std::atoi(argv[1]);
  double seconds = std::atof(argv[2]), invalid_at = std::atof(argv[3]);
  double reconnect_at = std::atof(argv[4]);
  igtl::ServerSocket::Pointer server = igtl::ServerSocket::New();
  if (server->CreateServer(port) < 0) {
    std::fprintf(stderr, "plus_server: cannot listen on %d\n", port);
    return 1;
  }
  std::printf("listening %d\n", port);
  std::fflush(stdout);
  double start = -1;
  int sent = 0, connections = 0;
  bool reconnected = false;
  while (start < 0 || now_s() - start < seconds) {
    igtl::ClientSocket::Pointer sock = server->WaitForConnection(20000);
    if (sock.IsNull()) {
      std::fprintf(stderr, "plus_server: nobody connected\n");
      return 1;
    }
    ++connections;
    double accepted = now_s();
    if (start < 0) start = accepted;
    send_pose(sock, "Tracker", 76.0);
    double next = now_s();
    while (true) {
      double t = now_s() - start, local = now_s() - accepted;
      if (t >= seconds) break;
      if (!reconnected && t >= reconnect_at) {
        reconnected = true;
        break;
      }
      double z = 76.0;
      if (local > 2.0) z -= 3.0 * (1.0 - std::cos(2.0 * M_PI * (local - 2.0) / 2.0));
      int ok = (t >= invalid_at && t < invalid_at + 1.0) ? send_invalid(sock)
                                                           : send_pose(sock, "ProbeToReference", z);
      if (!ok) break;
      ++sent;
      next += 0.01;
      std::this_thread::sleep_for(std::chrono::duration<double>(next - now_s()));
    }
    sock->CloseSocket();
  }
  std::printf("{\"poses_sent\": %d, \"connections\": %d}\n", sent, connections);
  return 0;
}
